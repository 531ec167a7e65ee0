"""Automatic pose initialisation from images alone.

``make_initializer(rig, model)`` returns an :class:`Initializer`, a callable
``initializer(frameset) -> InitResult | None`` for the tracker's hook. The work
is the pure function :func:`initialize` of one frame set (plus the constant
set-up), so a server can run it in a background thread while frames keep
arriving; the class only holds the set-up, an optional seed pose and the last
report.

Method (per call):

1. per camera with an image: undistort, oriented edge distance maps, corners
   and corner pairs joined by straight image edges (:mod:`.features`);
2. seeded mode first: if :meth:`Initializer.reseed` gave a predicted pose,
   refine from it (and a few perturbations of it) and verify; done if it
   passes;
3. hypotheses: every image corner path ``a-b-c`` (two linked corner pairs)
   against every model corner path ``A-B-C`` (two long sharp edges), solved by
   batched P3P in that camera (:mod:`.p3p`);
4. ranking: fast directional chamfer agreement of the projected visible model
   edges in the generating camera; the best per camera are moved to the world
   and re-ranked in every camera;
5. the best few are refined by multi-camera least squares on the oriented
   edge distances (with self-occlusion from the BSP) and verified: enough
   edge samples supported in every camera that sees the part, enough
   supported edges, a clear margin over any different pose. Otherwise None:
   a wrong lock is worse than a late one.
6. one camera alone: a part with plain faces may pass looser limits when its
   projected face interiors hold no image edges (``InitOptions.plain_faces``);
   such a pose is provisional: confirmed only when a later call finds it
   again, first among its candidates (``InitOptions.provisional_start``).
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np

from ..bsp import load_or_build_bsp
from ..edgefit import SHARED_EDGE_PX, CameraView, refine_pose, refine_subpixel
from ..frames import FrameSet
from ..metrics import add_sym
from ..model import Model
from ..rig import Rig
from ..se3 import exp_so3, invert_transform, transform_from_rt
from ..startpose import InitResult
from ..workspace import box_centre, centres_inside, check_workspace
from .features import EdgeOptions, Undistorter, extract_features
from .modelfeat import ModelFeatures, model_features
from .search import check_pose, image_paths, p3p_hypotheses, rank_in_camera, unshared_px

__all__ = ["InitOptions", "InitSetup", "InitReport", "InitResult", "Initializer", "make_initializer",
           "make_setup", "initialize"]


@dataclass(frozen=True)
class InitOptions:
    """Initialiser settings (thresholds in px unless stated).

    Attributes
    ----------
    edges : EdgeOptions
    max_image_paths : int
        Image corner paths kept per camera (shortest links first).
    one_end_paths : bool
        With one camera image, on every other call after one without a pose,
        image corner paths need only one of their two edges to end at the
        middle corner (the other may run on along a background line in line
        with it: a bracket flange against a rail had no path on its true
        corners). About twice the hypotheses (and the ranking time) on those
        calls; with several cameras the others give the paths, and a call
        that long delayed the demo's acquisition (the part entering the view
        makes the first calls fail).
    keep_after_sparse : int
        Hypotheses kept per camera after the first (sparse) ranking pass.
    keep_per_camera : int
        Hypotheses kept per camera after the second ranking pass.
    keep_occlusion_rank : int
        For a non-convex part, this many of the best after the second pass are
        scored again with the samples the part hides from itself left out
        (``rank_in_camera`` with the BSP tree), and so are all candidates in
        the re-ranking in every camera (0: culling only). The hidden edges of
        a bracket counted as unsupported ranked its true pose out.
    n_quick : int
        When none of the refined candidates passes the checks, the best this
        many of the joint ranking are refined briefly (one round of
        ``refine_pose``, at most ``quick_nfev`` steps, every camera), ranked
        again on their refined poses, and the best ``n_refine`` distinct of
        those refined fully and verified. A P3P pose from three corners
        located to a pixel or two can sit far enough off the part's outline
        to rank below clutter fits: on a one-camera bracket the hypotheses
        near the true pose ranked 38th and 43rd (refined: 1.6-2% of the
        diameter, accepted) and came first after a brief refinement (~1 ms
        each). Only as a fallback: run on every call, the extra candidates
        refined turned up rivals that held back two one-camera poses accepted
        before, and changed an eye-in-hand start (218/240 and 91/96 with one
        wrong lock, against 220/240 and 92/96, none, as a fallback). 0 turns
        it off.
    quick_when_pending : bool
        Run that fallback in a call confirming a provisional pose too (the
        pending pose itself does not count as a passing candidate): such a
        call confirms the pose when it comes first among what the search
        finds, so the search must look as hard as any other call. Skipped
        there, a one-camera L-block (rig seed 2017) provisionally started
        58% of the diameter off, its true pose's P3P hypotheses ranked out
        (5-9% off), was confirmed by the next call and published from frame
        44; searched, that call puts a pose 3% off first (the true pose
        explains 420-500 px of edges, the wrong one 267), the filter starts
        again there, the next call confirms it and the track is published
        from frame 39 at 1.4%.
    quick_nfev, quick_max_move : int, float
        Steps of that refinement, and the most it may move a hypothesis
        (mean model-vertex displacement, fraction of the diameter); one that
        moves further has run off (to a tiny, far copy that scores well on
        any edges) and is ranked unrefined.
    n_refine : int
        Hypotheses refined and verified (the best distinct ones) ...
    n_refine_extra, refine_windows : int
        ... plus, after a call without a pose, ``n_refine_extra`` from further
        down the ranking, a different window on each successive call (attempt
        ``k >= 1`` takes distinct ranks ``n_refine + n_refine_extra * ((k - 1)
        % refine_windows)`` on): the frames of one second give the search the
        budget of several calls, and a first call that succeeds costs no more.
    n_refine_confirm : int
        A call confirming a provisional pose (``pending_T_world_object``)
        refines the first this many distinct candidates of the ranking: it
        confirms the pose when that comes first among what the search finds,
        so it looks deeper than a call that only proposes. One camera, L-block
        4801 (a set not used for tuning): a pose 75% of the diameter off
        explaining the L's lower step alone (439 px of image edges) was taken
        provisionally and confirmed by the next call, the true pose (669 px)
        lying below the 9 distinct candidates refined (its P3P hypotheses
        were 20th in the camera's ranking, further down the distinct order).
        With 40 that call puts the true pose first (0.5% off) and the track is
        published from the next frame. A candidate only this deeper search
        finds counts only when it passes every strict check (not provisionally):
        on box 5214 (one camera) it found a pose 1.9 diameters off
        explaining more edge length (412 px against 285) than the pending pose
        (3% off), which it passed only provisionally (one open face, edges
        running on past 44% of its ends); taken in its place and confirmed by
        the next call, it was published (``confirm_deeper_strict`` False).
        Such a call costs about 0.1-0.3 s more. 0: as any call.
    confirm_deeper_strict : bool
        See ``n_refine_confirm``.
    rank_tol_px : float
        Distance at which a sample's agreement reaches zero in the ranking.
    verify_tol_px : float
        A sample within this oriented distance of an edge is an inlier.
    min_inlier_frac : float
        Least pooled inlier fraction of an accepted pose seen by several
        cameras (wrong poses score <= 0.5 there: another camera disagrees) ...
    min_inlier_frac_single : float
        ... and by one camera.
    min_camera_inlier_frac : float
        Least inlier fraction in every camera that sees the part (low: a
        dark side of the part on a dark background has no edges to find, and
        a wrong pose fitted in one camera scores ~0.3 or less in the others).
    hidden_camera : bool
        When no candidate passes and, of two or more judging cameras, one
        agrees with none of the candidates it can see (each under
        ``min_camera_inlier_frac``), every candidate is judged again without
        that camera (still requiring the pose in its view), as a rig without
        it would judge them (one camera left: under the one-camera limits,
        probe and confirmation), and the start says so (``InitResult.hidden``):
        something the model does not know stands between that camera and the
        part. In the demo with the three fixed cameras the
        arm following the part hid it from the top camera (inlier fraction
        0.15-0.23) for five seconds, and every call in that time was rejected,
        so a track lost then could not be found again while the arm waited
        above it. All candidates without the same camera, not each without
        its own worst: judged so, a hybrid-rig pose 18% off, fitting the two
        other cameras at 0.78, beat the true pose, whose hand-camera view
        agreed at 0.48 and whose statistics still counted the hidden camera's
        zeros.
    min_supported_edges : int
        Least number of supported model edges (all cameras) when several
        cameras judge the pose ...
    min_supported_edges_single : int
        ... and when only one does (one view is far easier to fit by chance:
        a single face matches any similar quadrilateral in the background).
    max_mean_dist_single : float
        With one judging camera, the most mean oriented edge distance of the
        visible samples (unsupported samples count at the clip value), px.
    max_overrun_frac, max_overrun_frac_single : float
        Most fraction of supported model edge ends past which the image edge
        runs straight on (several cameras / one camera).
    max_overrun_frac_confirm : float
        With one judging camera, a pose passing every other strict check
        (as for ``min_open_faces_confirm``, and combined with it) whose
        overrun lies above ``max_overrun_frac_single`` but not above this is
        provisional: returned only when the next call finds it again. A
        background line through a corner of the part (a rail edge behind a
        box) or two faces of the part lined up in the view (an L-block's
        step seen edge-on) runs on past true corners: 25-47% of the ends at
        the true pose in six of 26 one-camera misses.
    min_open_faces_single : int
        With one judging camera, the least number of large faces seen
        within 75 degrees of their normal (rejects accidental viewpoints).
    min_open_faces_confirm : int
        With one judging camera, a pose passing every other strict check
        (not the looser plain-face limits) with fewer open faces than
        ``min_open_faces_single`` but at least this many is provisional: it
        is returned only when the next call finds it again (as under
        ``confirm_plain``). One face seen head-on is a common view of a part
        lying at random; its pose is less sure (the depth rests on the thin
        strips of the side faces), and a lucky fit of a rectangle in the
        background does not survive a second frame. For a part with
        ``plain_faces`` such a pose must also have its face interiors clear
        of image edges (a bracket pose 71% off, fitted over clutter with 5% of
        its face interiors on edges, was confirmed on a fresh seed).
    min_supported_edges_confirm : int
        Such a pose (one open face) needs only this many supported edges
        instead of ``min_supported_edges_single``: a box lying flat and seen
        from above shows its top face's four edges and the strips of one or
        two side faces, 5-6 edges, every one of them supported; 11 of the 24
        one-camera trials missed in six seed sets were such views, their
        best candidates 2-9% of the diameter off. Provisional, so confirmed
        by the next call and then by the tracker (whose edge fits count a
        face seen as a strip as found, see
        :attr:`vespro.edgefit.EdgeFit.found_weight`).
    min_distinct_edges_confirm : int
        ... and this many of them standing apart in the image
        (:attr:`vespro.init.search.PoseCheck.distinct_supported`): a rectangle
        seen head-on leaves its tilt to the side faces' strips, and a strip
        whose far edge lies within two tolerances of the face's own edge
        supports any tilt. With 5 supported edges and no such count, one
        camera published 345 of 360 trials within the second instead of 336,
        none wrong; but with a paddle hiding one of two cameras (rig seed 4)
        a box started 9 deg / 19 mm off (14% of the diameter) was confirmed
        and published 12-22% off, its four corners and whole outline
        agreeing: 6 edges supported there, 4 apart (the true pose: 6 apart,
        but refined on that camera alone it slides to the wrong one).
        With 5 and 5: 569 of 600 one-camera trials published within the
        second instead of 564 (20 trials from each of seeds 0, 40, 200, 400,
        600, 800 and the held-out 1000, 1200, 1400, 1600; ``bench/init.py
        --track 52``), none wrong; the paddle trial and the 108 of ``--hide``
        as before (103, none wrong). The boxes seen straight from above
        (within about 10 deg of head-on, the strips under 4 px) stay out of
        one camera's reach.
    min_strips_apart_confirm, min_open_edges_apart_confirm : int
        ... and this many of the strips' far edges supported and standing apart
        from their creases (:attr:`vespro.init.search.PoseCheck.strips_apart`),
        unless the open face shows at least ``min_open_edges_apart_confirm``
        supported edges apart (:attr:`vespro.init.search.PoseCheck.open_edges_apart`):
        a face of more sides than a rectangle (an L-block's L, whose side faces
        are often seen edge on: L-block 17) fixes the pose by its own outline,
        a rectangle head-on matches another face of the part at another depth.
        The distinct count alone is fooled by a strip's end edge: box 4610 (one
        camera, a grey box on the dark belt whose top and side faces share a
        shade, so the image shows a plain quadrilateral) was matched by another
        face of the box, head-on and 0.24 m nearer (1.7 diameters off), its
        side faces seen edge on; a strip's end edge lying on the rail's edge
        behind made the fifth distinct edge, and the pose was confirmed by the
        next call. With 1 and 5 (and ``TrackerConfig.start_edge_offset_px``
        0.6), 1406 of 1500 one-camera trials published within the second,
        none wrong (4610 refused; two box starts seen from above with 1-2 px
        strips, which had passed by the end edges, no longer published: box 4
        and box 1617, whose track had reached 9.6%); two and three cameras
        864/864, the paddle trials 103/108, none wrong.
    max_outer_parallel_confirm : int
        ... and such a pose taken for its face's own outline (no strip's far
        edge apart, ``min_open_edges_apart_confirm``) may have at most this
        many of its silhouette edges with an image edge of their orientation
        running beside them just outside
        (:attr:`vespro.init.search.PoseCheck.outer_parallel`): a line all along
        an outline edge, a few pixels out, is the far edge of a side face the
        pose does not have. One camera, L-block 5008 (a set not used for
        tuning): the L face seen head-on, one side face the shade of the L face, so
        the image showed the L face and that strip as one larger L; a pose
        nearer and untilted matched it (its six edges apart), left the dark
        strip along the other side outside its outline, and was confirmed and
        published 11-13% of the diameter off. On 46 one-open-face candidates
        of 21 such views the true poses (2-8% off) had none, the wrong ones
        (10-90% off) one or two in 17 of 25; but on a fresh set (4800-4819)
        three true poses with strips apart had one (a belt's border along the
        part), hence only for poses without a strip apart. Negative: off.
    min_size_px : float
        Least projected size of the part (bounding-box diagonal, px) in every
        judging camera: tiny far-away fits of background texture are rejected,
        and a part that small could not be tracked anyway.
    min_supported_edge_frac : float
        Least fraction of the visible edges that are supported.
    ambiguity_margin : float
        A different pose (ADD-S above ``distinct_frac`` of the diameter) whose
        inlier fraction comes within this of the best makes the result
        ambiguous (None).
    ambiguity_margin_single : float
        The same when one camera judges: one view lets a wrong pose (an
        L-block turned over) fit its edges nearly as well as the true one
        (0.067 below it on a held-out trial).
    ambiguity_px_frac : float
        ... and whose explained edge length is within this fraction of the
        best's (a pose explaining far less of the image is no rival).
    distinct_frac : float
    subset_rival_frac, subset_margin_frac : float
        A distinct pose explaining at most ``subset_rival_frac`` of its
        explained edge length where the best explains none
        (:func:`vespro.init.search.unshared_px`), while the best explains at
        least ``subset_margin_frac`` of its own where that pose explains none,
        is part of the best's explanation, not a rival: one face of a box
        fitted alone (the dark side face beside it left unexplained), or a
        smaller copy fitted inside the part's outline. Such poses made 404 of
        a one-camera box trial's first four calls ambiguous at 0.98 vs 1.00
        (the best, 2.8% of the diameter off, explained 88 px of 319 that the
        rival did not). A negative ``subset_margin_frac`` turns the rule off.
    seed_perturb_rad, seed_perturb_m : float
        Spread of the extra starting points around a seeded pose.
    seed_only : bool
        With a seed, try only near it (no full search).
    shared_edge_px : float
        In the sub-pixel refinement an image edge point found by samples of
        two nearly parallel model edges within this distance (px) serves only
        the nearer one (``refine_subpixel``): counted for both, the thin strip
        of a face seen nearly edge-on was pulled onto one image edge and a
        single-camera pose 12% of the diameter off along the ray (refined
        from the true pose too) was locked. 0: off.
    require_fixed_view : bool
        The part is in the common view of the fixed cameras (the spec's
        set-up): a pose that a fixed camera with an image cannot see is
        rejected. Eye-in-hand cameras judge only poses they can see.
    plain_faces : bool
        The part's faces are plain (no texture or markings): with one camera,
        a rival pose whose faces cover image edges (twice the limit below)
        does not make a result ambiguous, and one camera may
        then accept a pose under the looser ``plain_*`` limits below when its
        projected face interiors are free of image edges. A face dark against
        a dark background leaves its edges unseen, so the true pose of a part
        seen by one camera often explains only 70-80% of its edges; a copy
        fitted to clutter, or shifted or flipped over the real part, covers
        image edges with its faces (the real part's own among them). With one
        judging camera every pose, under the strict limits too, must keep its
        face interiors clear (``plain_max_interior_edge_frac``): a bracket seen
        from above on a fresh seed (1617) was accepted 90% of the diameter off,
        its faces over the real part's slot and step (3.6% of their interiors
        on image edges, the true pose's 0); in 352 one-camera views (three
        parts, seeds 0-29 and 1000-1029) the pose refined from the truth had at
        most 0.13%. A part with texture or markings needs False (``vespro track``
        and ``vespro serve --textured``): one camera would refuse its true pose.
    plain_max_interior_edge_frac : float
        Most fraction of the face interiors on image edges (image noise at the
        true pose stays below 0.002 in the simulator).
    plain_max_shade_step : float
        ... and with one judging camera no face may lie over two shades: its
        grey levels split in two groups (each at least 15% of the face) whose
        spread is at most this fraction of the step between them
        (:attr:`vespro.init.search.PoseCheck.shade_step`), a boundary inside
        the face too faint to be an edge. L-block 6014 (one camera, the part
        turned over about its long axis explains the outline as well and more
        of the image edges) was taken 67% off: its back face lay over two of
        the part's faces 2.9 grey levels apart (ratio 0.06). Near-true
        candidates in 60 one-camera views: none under 0.15; a gradient across a
        face spreads its levels evenly (about 0.29). Image noise adds to the
        spread, so on a noisy image only a step of 10 times the noise counts.
        0: off.
    plain_min_inlier_frac, plain_max_mean_dist, plain_max_overrun_frac : float
    plain_min_supported_edges : int
        The looser single-camera limits.
    plain_min_crease_frac : float
        At least this fraction of the visible creases (edges between two
        faces that both face the camera) must be supported: a face may match its
        background, but two faces at an angle seldom share a shade, so a pose
        putting its creases across a plain image region is wrong (a flipped
        box over one plain face). Not all: under one light two faces can (an
        L-block's true pose often shows 2 of its 4 creases; more than half
        rejected it on every frame of two tuning trials).
    plain_rival_px_frac : float
        A pose accepted under the looser limits must explain more edge length
        than this fraction of any distinct rival whose faces are also clear.
    shade_rival_ratio, shade_rival_grey : float
        With one judging camera, when the best pose's faces each hold one
        shade (:attr:`vespro.init.search.PoseCheck.shade_rms` within
        ``shade_rival_grey`` grey levels of the image noise), a rival (or a
        probe's restart) whose face interiors are far less uniform (at least
        ``shade_rival_ratio`` times the best's RMS and ``shade_rival_grey``
        above it) is no rival: its faces straddle boundaries between the
        image's shades, too faint to be edges, that the best pose explains.
        A plain part under distant light shows one shade per face; the image
        noise adds to both (the ratio then asks for a stronger boundary on a
        noisier image). Measured in the simulator with one camera: true poses
        0.0 grey levels median, at most 0.82 (60 views, three parts); rivals
        of true poses in boxes seen with one face openly (35-160% of the
        diameter off, agreeing with as many edges) 1.9-7.7. Where the best's
        faces are not of one shade the rule stands aside: box 5214's best,
        1.9 diameters off at 6.0, would otherwise have lost its rival (22) and
        been published. A part with highlights or texture needs
        ``plain_faces`` False. 0 (either): off.
    probe_single : bool
        With one judging camera, an accepted pose is refined again from
        turns of itself (``probe_deg`` both ways and half turns about the two
        image axes through the part, a half turn about the line of sight): a
        restart settling on a distinct pose (``distinct_frac``) that scores
        about as well (the ambiguity margins) makes the result ambiguous. The
        search's own candidates need not hold that rival (an L-block turned
        over once locked wrong for want of it).
    probe_deg : float
        Tilt of those restarts, deg.
    confirm_plain : bool
        A pose accepted under the looser limits is returned only when the
        next call finds it again (within ``confirm_frac`` of the diameter,
        ADD-S): one more attempt, a few frames later, instead of a lucky fit.
        That call searches as well, and the pose found again must still come
        first among its candidates (a fit to static clutter is found again on
        every frame; the search may find the part).
    provisional_start : bool
        Such a pose is returned at once, marked ``InitResult.provisional``
        (mode ``"provisional"``), instead of None: the tracker starts the
        filter from it but publishes nothing until a later call confirms it
        (the tracker hands the call its current estimate,
        :meth:`Initializer.await_confirmation`) or puts another pose first
        (the filter then starts again from that one:
        :meth:`vespro.tracker.Tracker.offer`). Waiting for the next call
        before starting lost the frames between, and a view that the next
        call judged accidental (one face openly in view) lost the pose: a
        one-camera L-block (rig seed 410) found on frame 0 was published on
        frame 41; now 10. One camera, 240 trials (``bench/init.py --track``):
        published within a second on 227 instead of 222, none wrong.
    confirm_frac, confirm_speed : float
        Found again means within ``confirm_frac`` of the diameter plus
        ``confirm_speed`` (m/s) times the time since the previous call
        (ADD-S): a part on a conveyor moves between two calls.
    recall_rivals_s : float
        A call that finds the view ambiguous (two distinct poses agreeing with
        the images about alike, or a restart of the probe settling on another
        pose) hands both poses to the calls of the next this many
        seconds: each refines them again on its own frame set and counts them
        among its candidates, so the view stays ambiguous until a frame rules
        one out, and a call whose search happens to miss one of them does not
        take the other as unrivalled. Seen on a fresh seed (box, one camera,
        rig seed 3406): calls at frames 5-15 found the true pose and a rival
        turned about the line of sight (0.85-0.87 against 0.91-0.92) and
        returned nothing; the call at frame 25 found only the rival, 56% of the
        diameter off, took it and the track was published from frame 26. Not
        for a plain rival (a clear-faced pose explaining nearly as much edge
        length, often a fit to static clutter several diameters away): recalled,
        such a fit held back a box found within 2.5% on every call of the
        second (3816, published at frame 15 without). 0: off.
    recall_margin_factor : float
        A recalled pose is a rival within this many times the ambiguity margin
        (``ambiguity_margin*``): a view found ambiguous stays so until a frame
        rules the rival out clearly, not by the noise of one frame's agreement
        (box 3406: the wrong pose scored 0.04-0.07 above the true one on the
        ambiguous calls and 0.10 above it, over the one-camera margin of 0.08,
        on the call that took it). Or, agreeing within the ambiguity margin,
        within this many times the edge length margin (``ambiguity_px_frac``:
        explaining at least 1 - 0.2 x 2 = 0.6 of the best's edge length); not
        both margins widened at once. Box 7019 (one camera): a pose 1.6
        diameters off, the box's outline read inside out, explains 378 px of
        image edges where the true one explains 302 (0.799 of it, under the
        0.8 of a first finding) while agreeing with fewer of its own edges
        (0.98 against 0.99); calls at frames 15 and 20 found the two alike, the
        call at frame 25 took the wrong one and it was published. With both
        margins widened at once, L-block 6400's true pose (0.74 agreement,
        404 px) was refused for a recalled pose turned over (0.59, 291 px) and
        published 12 frames later.
    start_covariance : bool
        Hand the tracker the returned pose's covariance from its sub-pixel edge
        fit (:meth:`vespro.edgefit.EdgeFit.covariance`, as the tracker's own
        edge measurements) instead of leaving it to the tracker's wide default
        (10 mm, 0.05 rad): the first frame's corner windows then fit the pose's
        accuracy. With the default a bracket start 1.8% of the diameter off
        (edge fit: 2 mm, 0.3-0.5 deg) opened windows wide enough to accept two
        wrong image corners 9-12 px off; the first update moved the pose to
        8.6% and the track slid to 20%; with the fit's covariance 7 of 8 corners
        were found and the track published from the next frame at 0.2-3%.
    confirm_upheld : bool
        A call confirming a provisional pose where no candidate passes still
        confirms it (mode ``"upheld"``) when the pose, refined on this frame
        set from the filter's estimate, is found again near it, explains at
        least as much image edge length as any distinct candidate, has no
        rival (as a passing pose would, ``ambiguity_margin_single``), covers
        no image edges with its faces and agrees with ``upheld_min_inlier_frac``
        of its edges: one frame's weaker view (a face's edge lost against the
        belt, the mean distance a little over its limit) does not undo what the
        proposing call and the filter's frames since agree on. The tracker
        still publishes only after its own strong frames. Seen on one-camera
        bracket 1611: a start within 1% at frame 5 tracked at 1-3%, the call
        at frame 10 found it first at 0.62 agreement (under 0.7), later calls
        found the slot's clutter first, and nothing was published in 52 frames;
        upheld, it is published from frame 10.
    upheld_min_inlier_frac : float
        Least agreement of an upheld pose.
    held_rival : bool
        The filter's own pose during a provisional start (the pose the next
        call is asked to confirm) is a rival of the call's best even when it
        does not pass every check (a rival need not pass), though it is never
        returned as such: to be confirmed it must be found again by the call's
        own refinement, as before. Bracket 7809 (one camera): a provisional
        start 32% of the diameter off slid on the filter's own updates to
        within 1% by frame 14; the calls at frames 15-25 found poses 27-33%
        off first (0.77-0.80 agreement against the filter's 0.70) and put
        them in its place, and the call at frame 30 confirmed one: published
        at 13.9%, then 8.5-9%. With the filter's pose a rival those calls
        return nothing and the filter keeps its pose: published from frame 30
        at 1.9%, then at most 5.8% to frame 51.
    confirm_own_refinement : bool
        A call that finds the provisional pose again (its best within
        ``confirm_frac`` plus the motion allowance of it) returns the pose's
        own refinement on its frame set where that passes, not the best: the
        best may be a neighbour that the tracker, comparing it with its filter
        at the same instant, takes for another pose and starts again from.
        L-block 6601 (one camera): the filter 0.8% of the diameter off, its
        refinement 3.9% off (0.72 agreement, 302 px), the best 9.7% off (0.76,
        314 px) and 10.1% from the filter; the filter was restarted from the
        best and tracked at 5-10%, one frame at 10.2%. With the refinement the
        filter is confirmed as it is: published from frame 11 at 2.3%, at most
        4.7% to frame 51. Confirming the filter whatever the distance instead
        kept box 8200's filter 14.8% off, where its refinement (3.1%, the best)
        was right, and published it at 24%.
    keep_better_start : bool
        That rival is the filter's pose as it is where the verification scores
        it above its refinement on this frame set (oriented edge distances,
        then sub-pixel) on both agreement and edge length explained: the
        refinement's objective can slide a pose seen nearly edge-on, with few
        image edges and a long background line beside them, onto a worse fit
        by the verification's own measure. Bracket 7809, frame 25: refined,
        the true pose moves 22.6% of the diameter off, agreeing with 0.62 of
        its edges over 506 px against 0.70 over 555 px as it is; the filter's
        pose, within 1%, was refined away the same way and rivalled nothing.
        Only as a rival: returned as it was, a pose the filter had jumped to
        (box 6809, 11% in one frame to 15% off) was confirmed and published
        at 18.7%. For the search's candidates (P3P poses, ranked by
        agreement) it kept unrefined poses the refinement would have ruled
        out: boxes 3406 and 5214 locked on poses 55% and 1.9 diameters off.
    workspace : tuple of 6 float or None
        The cell's working volume ``(x0, y0, z0, x1, y1, z1)``, world frame, m
        (:mod:`vespro.workspace`): no hypothesis puts the part's centre outside it
        (on the demo's conveyor 85% of a call's P3P hypotheses do, and the call
        costs a quarter less); None: anywhere in view.
    """

    edges: EdgeOptions = field(default_factory=EdgeOptions)
    max_image_paths: int = 1500
    one_end_paths: bool = True
    keep_after_sparse: int = 2000
    keep_per_camera: int = 60
    keep_occlusion_rank: int = 300
    n_quick: int = 60
    quick_nfev: int = 10
    quick_max_move: float = 0.5
    quick_when_pending: bool = True
    n_refine: int = 6
    n_refine_extra: int = 3
    n_refine_confirm: int = 40
    confirm_deeper_strict: bool = True
    refine_windows: int = 5
    rank_tol_px: float = 3.0
    verify_tol_px: float = 2.0
    min_inlier_frac: float = 0.6
    min_inlier_frac_single: float = 0.7
    min_camera_inlier_frac: float = 0.4
    hidden_camera: bool = True
    min_supported_edges: int = 6
    min_supported_edges_single: int = 7
    min_supported_edges_confirm: int = 5
    min_distinct_edges_confirm: int = 5
    min_strips_apart_confirm: int = 1
    min_open_edges_apart_confirm: int = 5
    max_outer_parallel_confirm: int = 0
    min_size_px: float = 40.0
    min_size_px_single: float = 90.0
    max_mean_dist_single: float = 2.5
    min_open_faces_single: int = 2
    min_open_faces_confirm: int = 1
    max_overrun_frac: float = 0.5
    max_overrun_frac_single: float = 0.25
    max_overrun_frac_confirm: float = 0.5
    min_supported_edge_frac: float = 0.6
    ambiguity_margin: float = 0.05
    ambiguity_margin_single: float = 0.08
    ambiguity_px_frac: float = 0.2
    distinct_frac: float = 0.1
    subset_rival_frac: float = 0.05
    subset_margin_frac: float = 0.15
    seed_perturb_rad: float = 0.1
    seed_perturb_m: float = 0.01
    seed_only: bool = False
    require_fixed_view: bool = True
    subpixel: bool = True
    shared_edge_px: float = SHARED_EDGE_PX
    plain_faces: bool = True
    plain_max_interior_edge_frac: float = 0.005
    plain_max_shade_step: float = 0.1
    plain_min_inlier_frac: float = 0.65
    plain_max_mean_dist: float = 5.0
    plain_max_overrun_frac: float = 0.3
    plain_min_supported_edges: int = 6
    plain_min_crease_frac: float = 0.5
    plain_rival_px_frac: float = 0.8
    shade_rival_ratio: float = 2.0
    shade_rival_grey: float = 1.0
    probe_single: bool = True
    probe_deg: float = 25.0
    confirm_plain: bool = True
    provisional_start: bool = True
    confirm_frac: float = 0.05
    confirm_speed: float = 0.3
    recall_rivals_s: float = 1.0
    recall_margin_factor: float = 2.0
    start_covariance: bool = True
    confirm_upheld: bool = True
    upheld_min_inlier_frac: float = 0.6
    keep_better_start: bool = True
    held_rival: bool = True
    confirm_own_refinement: bool = True
    workspace: tuple | None = None

    def __post_init__(self):
        if self.workspace is not None:
            object.__setattr__(self, "workspace", check_workspace(self.workspace))


@dataclass(frozen=True)
class InitSetup:
    """Constant set-up of an initialiser: rig, model, derived data."""

    rig: Rig
    model: Model
    mf: ModelFeatures
    tree: object
    undistort: dict
    options: InitOptions
    centre: np.ndarray = None  # the centre of the part's bounding box, object frame (the working volume's test)


@dataclass(frozen=True)
class InitReport:
    """What one call did.

    Attributes
    ----------
    wall_s : float
        Wall time of the call, s.
    cpu_s : float
        CPU time of the calling thread, s (what the work costs on an idle
        core; the wall time includes waiting for a busy machine).
    mode : str
        ``"seed"`` (accepted near the seed), ``"search"``, ``"confirm"`` (a plain-face
        pose of the previous call found again), ``"provisional"`` (to be confirmed),
        ``"upheld"`` (a provisional pose found again first though nothing passed,
        ``InitOptions.confirm_upheld``) or ``"none"``.
    n_hypotheses : int
        P3P poses generated.
    accepted : bool
    inlier_frac : float
        Of the best verified candidate (NaN when none).
    per_camera : dict
    supported_edges, visible_edges : int
    reason : str
        Why nothing was returned ("" when accepted).
    candidates : tuple
        ``(T_world_object, PoseCheck)`` of every refined candidate, best first
        (diagnostics).
    rivals : tuple
        When the call found the view ambiguous: the best pose and its rival
        (``InitOptions.recall_rivals_s``); else empty.
    plain : bool
        The best pose passed every check under the looser single-camera
        limits (``plain_*``); not yet accepted when ``confirm_plain`` (it is
        then the first candidate, tried first by the next call).
    """

    wall_s: float
    cpu_s: float
    mode: str
    n_hypotheses: int
    accepted: bool
    inlier_frac: float = float("nan")
    per_camera: dict = field(default_factory=dict)
    supported_edges: int = 0
    visible_edges: int = 0
    reason: str = ""
    candidates: tuple = ()
    plain: bool = False
    rivals: tuple = ()


def make_setup(rig: Rig, model: Model, options: InitOptions | None = None, tree=None) -> InitSetup:
    """Build the constant set-up (model features, BSP tree, undistortion maps)."""
    options = options or InitOptions()
    mf = model_features(model)
    if tree is None and not mf.convex:
        tree = load_or_build_bsp(model)
    und = {c.name: Undistorter(c.intrinsics) for c in rig}
    return InitSetup(rig, model, mf, tree, und, options, box_centre(model.vertices))


def _per_camera(fn, items) -> list:
    """``[fn(x) for x in items]``, the cameras side by side on the process's cores.

    Each camera's image work (OpenCV, the compiled kernels) lets go of the
    interpreter, so threads run it in parallel: a search's wall time is then set
    by the cores' spare time together, not one core's (a live start beside a
    real-time loop and a simulated plant, each holding part of a core).
    """
    items = list(items)
    if len(items) < 2 or _cores() < 2:
        return [fn(x) for x in items]
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(max_workers=_cores(), thread_name_prefix="vespro-init-camera")
    return list(_POOL.map(fn, items))


def _cores() -> int:
    """The cores this thread may run on now (not at import: a live server imports this
    module pinned to its loop's core, and its start worker is then let onto every core)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


_POOL: ThreadPoolExecutor | None = None


def _forget_pool() -> None:
    global _POOL
    _POOL = None  # a forked child (the server's start worker) has none of its parent's threads


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def _views(setup: InitSetup, frameset: FrameSet) -> list[CameraView]:
    seen = []
    for cam in setup.rig:
        img = frameset.images.get(cam.name)
        if img is None:
            continue
        if cam.is_fixed:
            T_wc = cam.T_world_camera
        else:
            T_wc = frameset.T_world_camera.get(cam.name)
            if T_wc is None or not np.all(np.isfinite(T_wc)):
                continue
        seen.append((cam, img, T_wc))

    def view(item):
        cam, img, T_wc = item
        feat = extract_features(cam.name, setup.undistort[cam.name](img), cam.intrinsics.K, setup.options.edges)
        return CameraView(feat, np.asarray(T_wc, float), cam.is_fixed)

    return _per_camera(view, seen)


def _accept(chk, opt: InitOptions) -> tuple[bool, str]:
    if chk.n_cameras == 0:
        return False, "part not in any image"
    if chk.unseen_fixed:
        return False, "outside the view of a fixed camera"
    if opt.plain_faces and chk.n_cameras == 1 and (unclear := _faces_unclear(chk, opt)):
        return False, "one camera, " + unclear
    need_frac = opt.min_inlier_frac if chk.n_cameras > 1 else opt.min_inlier_frac_single
    if chk.inlier_frac < need_frac:
        return False, f"inlier fraction {chk.inlier_frac:.2f} < {need_frac}"
    worst = min((v for v in chk.per_camera.values() if np.isfinite(v)), default=0.0)
    if worst < opt.min_camera_inlier_frac:
        return False, f"a camera disagrees (inlier fraction {worst:.2f})"
    max_over = opt.max_overrun_frac if chk.n_cameras > 1 else opt.max_overrun_frac_single
    if chk.overrun_frac > max_over:
        return False, f"image edges run on past {chk.overrun_frac:.0%} of the model edge ends"
    if chk.n_cameras == 1 and chk.open_faces < opt.min_open_faces_single:
        return False, f"one camera, accidental view ({chk.open_faces} faces seen openly)"
    if chk.n_cameras == 1 and chk.mean_dist > opt.max_mean_dist_single:
        return False, f"one camera, mean edge distance {chk.mean_dist:.2f} px > {opt.max_mean_dist_single}"
    need = opt.min_supported_edges if chk.n_cameras > 1 else opt.min_supported_edges_single
    if chk.supported_edges < need:
        return False, f"{chk.supported_edges} supported edges < {need}"
    min_size = opt.min_size_px if chk.n_cameras > 1 else opt.min_size_px_single
    if chk.min_size_px < min_size:
        return False, f"projected size {chk.min_size_px:.0f} px < {min_size}"
    if chk.supported_edges < opt.min_supported_edge_frac * chk.visible_edges:
        return False, f"{chk.supported_edges}/{chk.visible_edges} edges supported"
    return True, ""


def _faces_unclear(chk, opt: InitOptions) -> str:
    """Why a pose's faces are not those of a plain part ("" when they are): image edges inside
    them (``InitOptions.plain_max_interior_edge_frac``), or a face over two shades
    (``plain_max_shade_step``; 0: off)."""
    if chk.interior_edge_frac > opt.plain_max_interior_edge_frac:
        return f"image edges inside the faces ({chk.interior_edge_frac:.3f})"
    if 0 < opt.plain_max_shade_step and chk.shade_step <= opt.plain_max_shade_step:
        return f"a face over two shades ({chk.shade_step:.2f})"
    return ""


def _accept_plain(chk, opt: InitOptions) -> tuple[bool, str]:
    """The looser single-camera limits for a part with plain faces (see ``InitOptions.plain_faces``)."""
    if not opt.plain_faces or chk.n_cameras != 1 or chk.unseen_fixed:
        return False, "not a single-camera view"
    if unclear := _faces_unclear(chk, opt):
        return False, unclear
    if chk.inlier_frac < opt.plain_min_inlier_frac:
        return False, f"inlier fraction {chk.inlier_frac:.2f} < {opt.plain_min_inlier_frac}"
    if chk.crease_edges and chk.crease_supported < opt.plain_min_crease_frac * chk.crease_edges:
        return False, f"{chk.crease_supported}/{chk.crease_edges} creases supported"
    if chk.mean_dist > opt.plain_max_mean_dist:
        return False, f"mean edge distance {chk.mean_dist:.2f} px > {opt.plain_max_mean_dist}"
    if chk.overrun_frac > opt.plain_max_overrun_frac:
        return False, f"image edges run on past {chk.overrun_frac:.0%} of the model edge ends"
    if chk.open_faces < opt.min_open_faces_single:
        return False, f"accidental view ({chk.open_faces} faces seen openly)"
    if chk.supported_edges < max(opt.plain_min_supported_edges, opt.min_supported_edge_frac * chk.visible_edges):
        return False, f"{chk.supported_edges}/{chk.visible_edges} edges supported"
    if chk.min_size_px < opt.min_size_px_single:
        return False, f"projected size {chk.min_size_px:.0f} px < {opt.min_size_px_single}"
    return True, ""


def _verdict(chk, opt: InitOptions) -> tuple[bool, bool, str]:
    """(accepted, only provisionally: to be confirmed by the next call, why not).

    Provisional: passed under the looser plain-face limits only, or (one
    judging camera) passed every strict check but seen along all faces but
    one (``InitOptions.min_open_faces_confirm``) or with image edges running
    on past more of its corners (``InitOptions.max_overrun_frac_confirm``). Not both: an L-block pose
    70% of the diameter off passed the plain-face limits with one open face
    on a fresh seed (45) and was confirmed.
    """
    ok, why = _accept(chk, opt)
    if ok:
        return True, False, ""
    okp, _ = _accept_plain(chk, opt)
    if okp:
        return True, True, ""
    few_faces = opt.min_open_faces_confirm <= chk.open_faces < opt.min_open_faces_single
    overrun = opt.max_overrun_frac_single < chk.overrun_frac <= opt.max_overrun_frac_confirm
    if chk.n_cameras == 1 and (few_faces or overrun):  # (face interiors clear: checked by _accept)
        loose = replace(opt, min_open_faces_single=min(opt.min_open_faces_single, opt.min_open_faces_confirm),
                        max_overrun_frac_single=max(opt.max_overrun_frac_single, opt.max_overrun_frac_confirm),
                        min_supported_edges_single=(min(opt.min_supported_edges_single,
                                                        opt.min_supported_edges_confirm) if few_faces
                                                    else opt.min_supported_edges_single))
        thin = chk.distinct_supported < opt.min_distinct_edges_confirm or \
            (chk.strips_apart < opt.min_strips_apart_confirm
             and chk.open_edges_apart < opt.min_open_edges_apart_confirm)
        # Taken for its own outline (no strip apart): unless a line beside that outline
        # says a side face was left out.
        by_outline = few_faces and chk.strips_apart < opt.min_strips_apart_confirm
        beside = by_outline and 0 <= opt.max_outer_parallel_confirm < chk.outer_parallel
        if _accept(chk, loose)[0] and not (few_faces and thin) and not beside:
            return True, True, ""
    return False, False, why


def _refined(T_world_object: np.ndarray, views, setup: InitSetup) -> np.ndarray:
    """A candidate refined on the oriented edge distances, then (``InitOptions.subpixel``) to sub-pixel."""
    opt, mf = setup.options, setup.mf
    T = refine_pose(T_world_object, views, mf, setup.tree)
    if opt.subpixel:
        T = refine_subpixel(T, views, mf, setup.tree, shared_edge_px=opt.shared_edge_px)
    return T


def _own_pose(T_world_object: np.ndarray, refined: tuple, views, setup: InitSetup) -> tuple:
    """The filter's pose as a rival (``InitOptions.held_rival``): (T, check) of its refinement
    ``refined``, or of the pose as it is where the verification scores that above its
    refinement on both agreement and edge length explained (``InitOptions.keep_better_start``)."""
    if setup.options.keep_better_start:
        c0 = _checked(T_world_object, views, setup)
        if c0.inlier_frac > refined[1].inlier_frac and c0.inlier_px > refined[1].inlier_px:
            return np.array(T_world_object, float), c0
    return refined


def _checked(T_world_object: np.ndarray, views, setup: InitSetup):
    """How well a pose explains every camera's image (:func:`check_pose` with the set-up's options)."""
    opt = setup.options
    return check_pose(T_world_object, views, setup.mf, setup.tree, opt.verify_tol_px,
                      require_fixed=opt.require_fixed_view)


def _without_hidden(refined: list, views, setup: InitSetup) -> list:
    """The refined candidates judged again without the camera where the part is hidden
    (``InitOptions.hidden_camera``), or as they are when there is none.

    The hidden camera is one that agrees with none of the candidates it can see
    (under ``min_camera_inlier_frac`` for each), among two or more that judge;
    every candidate is then judged without it, as a rig without that camera would
    judge them, so that they still compete on equal terms.
    """
    opt = setup.options
    seen: dict[str, list] = {}
    for _, c in refined:
        for name, f in c.per_camera.items():
            if np.isfinite(f):
                seen.setdefault(name, []).append(f)
    if len(seen) < 2:
        return refined
    hidden = min(seen, key=lambda name: max(seen[name]))
    if max(seen[hidden]) >= opt.min_camera_inlier_frac:
        return refined
    rest = [v for v in views if v.feat.name != hidden]
    return [(T, replace(_checked(T, rest, setup), unseen_fixed=c.unseen_fixed, hidden=hidden)) for T, c in refined]


def _judging(views, chk) -> list:
    """The views that judged ``chk``: all of them less its hidden camera."""
    return [v for v in views if v.feat.name != chk.hidden]


def _joint_scores(cand: np.ndarray, views, setup: InitSetup) -> np.ndarray:
    """Mean ranking agreement of world poses ``cand`` (N, 4, 4) over the cameras that can judge them."""
    opt = setup.options
    total = np.zeros(len(cand))
    count = np.zeros(len(cand))
    for v in views:
        T_cw = invert_transform(v.T_world_camera)
        Tc = np.einsum("ij,njk->nik", T_cw, cand)
        sc, _ = rank_in_camera(Tc[:, :3, :3], Tc[:, :3, 3], v.feat, setup.mf, opt.rank_tol_px, min_inside=0.5,
                               tree=setup.tree if opt.keep_occlusion_rank > 0 else None)
        judged = np.isfinite(sc)
        total += np.where(judged, sc, 0.0)
        # The part is in the common view of the fixed cameras: one that cannot
        # see the pose counts against it.
        count += judged | (v.fixed and opt.require_fixed_view)
    return np.where(count > 0, total / np.maximum(count, 1), -1.0)


def _start_covariance(T_world_object: np.ndarray, views, setup: InitSetup) -> np.ndarray | None:
    """The returned pose's covariance from one more sub-pixel edge fit round at it (see
    ``InitOptions.start_covariance``); None (the tracker's default) when off or the fit fails."""
    opt = setup.options
    if not opt.start_covariance:
        return None
    _, fit = refine_subpixel(T_world_object, views, setup.mf, setup.tree, rounds=1, shared_edge_px=opt.shared_edge_px,
                             info=True)
    return None if fit is None else fit.covariance(T_world_object[:3, :3])


def _margin(chk, opt: InitOptions) -> float:
    return opt.ambiguity_margin if chk.n_cameras > 1 else opt.ambiguity_margin_single


def _part_of(c2, chk, opt: InitOptions) -> bool:
    """Pose check ``c2`` explains no more than part of what ``chk`` explains (``InitOptions.subset_*``)."""
    if opt.subset_margin_frac < 0:
        return False
    return (unshared_px(c2, chk, opt.verify_tol_px) <= opt.subset_rival_frac * c2.inlier_px
            and unshared_px(chk, c2, opt.verify_tol_px) >= opt.subset_margin_frac * chk.inlier_px)


def _shaded_apart(c2, chk, opt: InitOptions) -> bool:
    """With one judging camera, pose check ``chk``'s faces hold one shade each and ``c2``'s are
    far less uniform (a plain part; ``InitOptions.shade_rival_*``): ``c2`` is no rival of ``chk``."""
    if not (opt.plain_faces and chk.n_cameras == 1 and opt.shade_rival_ratio > 0 and opt.shade_rival_grey > 0):
        return False
    a, b = c2.shade_rms, chk.shade_rms
    return bool(np.isfinite(a) and np.isfinite(b) and b <= chk.shade_noise + opt.shade_rival_grey
                and a >= opt.shade_rival_ratio * b and a >= b + opt.shade_rival_grey)


def _rival(T_best: np.ndarray, chk, plain: bool, others, again, mf: ModelFeatures, opt: InitOptions):
    """(T, check, by agreement) of the first of ``others`` that makes ``T_best`` ambiguous, or
    (None, None, False): a distinct pose seen by the same cameras that agrees with the images
    about as well and explains about as much edge length (a rival), or under the looser limits
    (``plain``) any clear-faced pose explaining nearly as much (a plain rival); either way not
    a pose explaining only part of what ``T_best`` explains. ``again``: poses recalled from an
    earlier call's ambiguity, rivals within a wider margin (``recall_margin_factor``)."""
    for T2, c2 in others:
        if c2.unseen_fixed or c2.n_cameras < chk.n_cameras or \
                _adds(mf, T_best, T2) <= opt.distinct_frac * mf.diameter:
            continue
        # A pose whose faces cover image edges is no rival for a plain
        # part (one camera: with several, a part partly hidden in one
        # view keeps counting as a rival).
        if opt.plain_faces and chk.n_cameras == 1 and \
                c2.interior_edge_frac > 2 * opt.plain_max_interior_edge_frac:
            continue
        if _shaded_apart(c2, chk, opt):
            continue
        # A rival need not pass every check (the true pose of an
        # accidental view may fail one): seen by the same cameras, about
        # as good an agreement, about as much edge length explained.
        # (A recalled pose: either margin widened, not both at once.)
        widen = opt.recall_margin_factor if _same_as_any(mf, T2, again) else 1.0

        def within(w_frac: float, w_px: float) -> bool:
            return (c2.inlier_frac >= chk.inlier_frac - w_frac * _margin(chk, opt)
                    and c2.inlier_px >= (1 - w_px * opt.ambiguity_px_frac) * chk.inlier_px)

        rival = within(widen, 1.0) or within(1.0, widen)
        plain_rival = plain and c2.interior_edge_frac <= 2 * opt.plain_max_interior_edge_frac and \
            c2.inlier_frac >= 0.5 and c2.inlier_px >= opt.plain_rival_px_frac * chk.inlier_px
        if (rival or plain_rival) and not _part_of(c2, chk, opt):
            return T2, c2, rival
    return None, None, False


def _upheld(held: tuple, refined: list, again, mf: ModelFeatures, opt: InitOptions) -> bool:
    """The provisional pose ``held`` (refined on this frame set, found near where the filter
    has it) is upheld though no candidate passes here: it explains at least as much image
    edge length as any distinct candidate, no rival makes it ambiguous, its faces are clear
    (:func:`_faces_unclear`) and it agrees with at least ``upheld_min_inlier_frac`` of its
    edges (``InitOptions.confirm_upheld``)."""
    Th, ch = held
    if ch.n_cameras != 1 or ch.inlier_frac < opt.upheld_min_inlier_frac or \
            _faces_unclear(ch, opt):
        return False
    if any(c.inlier_px > ch.inlier_px and _adds(mf, Th, T) > opt.distinct_frac * mf.diameter
           for T, c in refined):
        return False
    return _rival(Th, ch, False, refined, again, mf, opt)[0] is None  # (_rival skips its near copies)


def _probe(T_world_object: np.ndarray, chk, views, setup: InitSetup) -> tuple[bool, str, np.ndarray | None]:
    """Refine again from turns of a single-camera pose: (no rival found, why not, the rival);
    see ``InitOptions.probe_single``."""
    opt, mf = setup.options, setup.mf
    v = next((v for v in views if np.isfinite(chk.per_camera.get(v.feat.name, np.nan))), None)
    if v is None:
        return True, "", None
    c_w = T_world_object[:3, :3] @ (0.5 * (mf.vertices.min(0) + mf.vertices.max(0))) + T_world_object[:3, 3]
    ray = c_w - v.T_world_camera[:3, 3]
    ray /= np.linalg.norm(ray)
    a1 = np.cross(ray, v.T_world_camera[:3, 1])
    a1 /= np.linalg.norm(a1)
    a2 = np.cross(ray, a1)
    tilt = np.deg2rad(opt.probe_deg)
    turns = [a * ang for a in (a1, a2) for ang in (tilt, -tilt, np.pi)] + [ray * np.pi]
    for w in turns:
        dR = exp_so3(w)
        T0 = transform_from_rt(dR @ T_world_object[:3, :3], c_w + dR @ (T_world_object[:3, 3] - c_w))
        Tr = refine_pose(T0, views, mf, setup.tree)
        if _adds(mf, Tr, T_world_object) <= opt.distinct_frac * mf.diameter:
            continue
        if opt.subpixel:
            Tr = refine_subpixel(Tr, views, mf, setup.tree, shared_edge_px=opt.shared_edge_px)
        c2 = check_pose(Tr, views, mf, setup.tree, opt.verify_tol_px, require_fixed=opt.require_fixed_view)
        if c2.n_cameras and _adds(mf, Tr, T_world_object) > opt.distinct_frac * mf.diameter and \
                c2.inlier_frac >= chk.inlier_frac - _margin(chk, opt) and \
                c2.inlier_px >= (1 - opt.ambiguity_px_frac) * chk.inlier_px and \
                not (opt.plain_faces and c2.interior_edge_frac > 2 * opt.plain_max_interior_edge_frac) and \
                not _shaded_apart(c2, chk, opt) and not _part_of(c2, chk, opt):
            return False, (f"ambiguous: a restart settles on a pose scoring {c2.inlier_frac:.2f} vs "
                           f"{chk.inlier_frac:.2f}"), Tr
    return True, "", None


def _adds(mf: ModelFeatures, T1, T2) -> float:
    """Distance between two poses: ADD over the model vertices, least over the part's symmetries, m
    (:func:`vespro.metrics.add_sym`: not ADD-S, or a rival would be overlooked)."""
    return add_sym(T1, T2, mf.vertices, mf.symmetries)


def _same_as_any(mf: ModelFeatures, T: np.ndarray, poses) -> bool:
    """Pose ``T`` is within 2% of the diameter (:func:`_adds`) of one of ``poses``: the same candidate."""
    return any(_adds(mf, T, T2) < 0.02 * mf.diameter for T2 in poses)


@dataclass
class _Call:
    """One call's clock and frame set views: how its answers are made."""

    setup: InitSetup
    views: list
    t0: float  # time.perf_counter() at the call's start
    c0: float  # time.thread_time() at the call's start

    def found(self, T: np.ndarray, chk, mode: str, nh: int) -> tuple[InitResult, InitReport]:
        """The pose ``T`` (its check ``chk``), returned."""
        return InitResult(T_world_object=T, cov6=_start_covariance(T, _judging(self.views, chk), self.setup),
                          hidden=(chk.hidden,) if chk.hidden else ()), InitReport(
            time.perf_counter() - self.t0, time.thread_time() - self.c0, mode, nh, True, chk.inlier_frac,
            chk.per_camera, chk.supported_edges, chk.visible_edges)

    def none(self, nh: int, why: str, chk=None, **kw) -> tuple[None, InitReport]:
        """Nothing returned, for reason ``why`` (the best candidate's check ``chk`` where there is one)."""
        stats = () if chk is None else (chk.inlier_frac, chk.per_camera, chk.supported_edges, chk.visible_edges)
        return None, InitReport(time.perf_counter() - self.t0, time.thread_time() - self.c0, "none", nh, False,
                                *stats, reason=why, **kw)


@dataclass
class _Pending:
    """A provisional pose from the previous call (``pending_T_world_object``), refined again on
    this frame set: ``refined`` (T, check); ``held`` that when it stayed ``near`` the pose
    given; ``passing`` that when it also passes (it then joins the search's candidates)."""

    T: np.ndarray
    refined: tuple
    near: float
    held: tuple | None
    passing: tuple | None


def _pending(setup: InitSetup, views, T_world_object: np.ndarray, age_s: float) -> _Pending:
    """The previous call's provisional pose, refined again here (see :class:`_Pending`)."""
    opt, mf = setup.options, setup.mf
    Tp = np.asarray(T_world_object, float)
    near = opt.confirm_frac * mf.diameter + opt.confirm_speed * max(age_s, 0.0)
    Tr = _refined(Tp, views, setup)
    refined = (Tr, _checked(Tr, views, setup))
    held = refined if _adds(mf, Tr, Tp) < near else None
    passing = held if held is not None and _verdict(held[1], opt)[0] else None
    return _Pending(Tp, refined, near, held, passing)


def _seeded(call: _Call, seed_T_world_object: np.ndarray, rng: np.random.Generator):
    """Refine from the prediction and a few perturbations of it: the call's answer when one
    passes (or ``InitOptions.seed_only``), else None (the full search follows)."""
    setup, views = call.setup, call.views
    opt = setup.options
    starts = [np.asarray(seed_T_world_object, float)]
    for _ in range(4):
        dR = exp_so3(rng.normal(size=3) * opt.seed_perturb_rad)
        dp = rng.normal(size=3) * opt.seed_perturb_m
        starts.append(transform_from_rt(starts[0][:3, :3] @ dR, starts[0][:3, 3] + dp))
    seeded = []
    for T in starts:
        Tr = _refined(T, views, setup)
        chk = _checked(Tr, views, setup)
        seeded.append((Tr, chk))
        if _verdict(chk, opt)[0]:
            return call.found(Tr, chk, "seed", len(starts))
    if opt.hidden_camera:
        # A camera the part is hidden from (the arm that hid it when the track was
        # lost): judged without it, as the search's candidates are.
        for Tr, chk in sorted(_without_hidden(seeded, views, setup), key=lambda r: -r[1].inlier_frac):
            if _verdict(chk, opt)[0]:
                return call.found(Tr, chk, "seed", len(starts))
    if opt.seed_only:
        best = max(seeded, key=lambda r: r[1].inlier_frac)[1]
        return call.none(len(starts), "seed: " + _accept(best, opt)[1], best)
    return None


def _hypotheses(setup: InitSetup, views, attempt: int) -> tuple[np.ndarray, int]:
    """P3P hypotheses per camera, ranked in that camera: the best few of each camera
    (``T_world_object``, shape (N, 4, 4)) and how many were generated."""
    opt, mf = setup.options, setup.mf

    def ranked(v):
        """(this camera's best hypotheses as T_world_object, hypotheses generated)."""
        ip = image_paths(v.feat, max_paths=opt.max_image_paths,
                         one_end=opt.one_end_paths and attempt % 2 == 1 and len(views) == 1)
        R, t = p3p_hypotheses(v.feat, mf, setup.model.vertices, ip)
        n = len(R)
        if n and opt.workspace is not None:  # the prior: only poses in the working volume
            T_wc = v.T_world_camera
            keep = centres_inside(T_wc[:3, :3] @ R, t @ T_wc[:3, :3].T + T_wc[:3, 3], setup.centre, opt.workspace)
            R, t = R[keep], t[keep]
        if len(R) == 0:
            return [], n
        # Two passes: a few samples on the long edges for all, the coarse set for the best.
        sc, _ = rank_in_camera(R, t, v.feat, mf, opt.rank_tol_px, samples=mf.sparse)
        sc = np.where(np.isfinite(sc), sc, -1.0)
        top = np.argsort(-sc)[:opt.keep_after_sparse]
        top = top[sc[top] > 0]
        sc2, _ = rank_in_camera(R[top], t[top], v.feat, mf, opt.rank_tol_px)
        sc2 = np.where(np.isfinite(sc2), sc2, -1.0)
        if setup.tree is not None and not mf.convex and opt.keep_occlusion_rank > 0:
            # A third pass for a non-convex part: the best few hundred again,
            # without the samples the part hides from itself.
            o2 = np.argsort(-sc2)[:opt.keep_occlusion_rank]
            top = top[o2[sc2[o2] > 0]]
            sc2, _ = rank_in_camera(R[top], t[top], v.feat, mf, opt.rank_tol_px, tree=setup.tree)
            sc2 = np.where(np.isfinite(sc2), sc2, -1.0)
        o2 = np.argsort(-sc2)[:opt.keep_per_camera]
        top = top[o2[sc2[o2] > 0]]
        return [v.T_world_camera @ transform_from_rt(R[k], t[k]) for k in top], n

    per = _per_camera(ranked, views)
    cand = [T for c, _ in per for T in c]
    return np.asarray(cand).reshape(-1, 4, 4), sum(n for _, n in per)


def _verified(setup: InitSetup, views, cand: np.ndarray, attempt: int, pend: _Pending | None,
              recall: tuple) -> tuple[list, list]:
    """The candidates re-ranked in every camera, the best few distinct ones refined and
    checked, with the pending pose and the recalled rivals joining them: (refined, again),
    ``refined`` as (T, check) best first, ``again`` the recalled poses refined here."""
    opt, mf = setup.options, setup.mf
    passing = pend.passing if pend is not None else None
    # Re-rank in every camera: mean agreement over the cameras that can judge.
    order = np.argsort(-_joint_scores(cand, views, setup))
    refined = []

    def refine_distinct(order, wanted, strict_only=frozenset()):
        # (candidates of the ranks in strict_only count only when they pass every strict check)
        distinct = []
        for k in order:
            if len(distinct) > max(wanted):
                break
            if _same_as_any(mf, cand[k], distinct):
                continue
            distinct.append(cand[k])
            if len(distinct) - 1 not in wanted:
                continue
            Tr = _refined(cand[k], views, setup)
            if not _same_as_any(mf, Tr, [T for T, _ in refined]):
                chk_k = _checked(Tr, views, setup)
                if opt.confirm_deeper_strict and len(distinct) - 1 in strict_only and \
                        _verdict(chk_k, opt)[:2] != (True, False):
                    continue
                refined.append((Tr, chk_k))

    wanted = set(range(opt.n_refine))
    if attempt > 0:  # a first call that succeeds needs no more
        w0 = opt.n_refine + opt.n_refine_extra * ((attempt - 1) % max(opt.refine_windows, 1))
        wanted |= set(range(w0, w0 + opt.n_refine_extra))
    # A confirming call looks deeper, but what only that finds must pass every strict check.
    deeper = set(range(opt.n_refine_confirm)) - wanted if passing is not None else set()
    refine_distinct(order, wanted | deeper, deeper)
    if opt.n_quick > 0 and (passing is None or opt.quick_when_pending) and \
            not any(_verdict(c, opt)[0] for _, c in refined):
        # None passes: the best n_quick again after a brief refinement, and the
        # best few of those (the ones not refined already) refined and verified.
        q = order[:opt.n_quick]
        for k in q:
            Tq = refine_pose(cand[k], views, mf, setup.tree, rounds=1, max_nfev=opt.quick_nfev)
            if _adds(mf, Tq, cand[k]) <= opt.quick_max_move * mf.diameter:
                cand[k] = Tq
        refine_distinct(q[np.argsort(-_joint_scores(cand[q], views, setup), kind="stable")], set(range(opt.n_refine)))
    if passing is not None and not _same_as_any(mf, passing[0], [T for T, _ in refined]):
        refined.append(passing)
    # An earlier call's ambiguity, measured again on this frame set: a rival this
    # call's search missed still counts.
    again = [_refined(np.asarray(T, float), views, setup) for T in recall]
    for Tr in again:
        if not _same_as_any(mf, Tr, [T for T, _ in refined]):
            refined.append((Tr, _checked(Tr, views, setup)))
    if opt.hidden_camera and not any(_verdict(c, opt)[0] for _, c in refined):
        refined = _without_hidden(refined, views, setup)
    # Candidates that pass every check first, then by the image edge length
    # they explain (a smaller, farther copy fitted to part of the part
    # explains less), then by agreement.
    refined.sort(key=lambda r: (not _verdict(r[1], opt)[0], -r[1].inlier_px, -r[1].inlier_frac))
    return refined, again


def _decided(call: _Call, refined: list, again: list, pend: _Pending | None, nh: int):
    """The call's answer from its verified candidates (best first): the best, unless a rival
    makes it ambiguous or it fails; a provisional pose confirmed, upheld or replaced."""
    setup, views = call.setup, call.views
    opt, mf = setup.options, setup.mf
    T_best, chk = refined[0]
    ok, plain, why = _verdict(chk, opt)
    rivals = ()
    # The pending pose found again and still first: its own call looked for
    # rivals already.
    confirmed = ok and pend is not None and _adds(mf, T_best, pend.T) < pend.near
    if confirmed and opt.confirm_own_refinement and pend.passing is not None:
        # Found again: the pending pose's own refinement, where that passes, is what the
        # tracker gets (not a neighbour the search ranked above it).
        T_best, chk = pend.passing
        ok, plain, why = _verdict(chk, opt)
    if ok and not confirmed:
        # The filter's own pose, though it need not pass, is a rival (never returned as it is).
        own = _own_pose(pend.T, pend.refined, views, setup) if pend is not None and opt.held_rival else None
        own_rival = [own] if own is not None and not _same_as_any(mf, own[0], [T for T, _ in refined]) else []
        T2, c2, rival = _rival(T_best, chk, plain, refined[1:] + own_rival, again, mf, opt)
        if T2 is not None:
            ok, why = False, (f"ambiguous: another pose scores {c2.inlier_frac:.2f} vs {chk.inlier_frac:.2f}"
                              if rival else f"ambiguous (plain faces): another pose explains "
                              f"{c2.inlier_px:.0f} px vs {chk.inlier_px:.0f}")
            # Recalled by the next calls: a rival by agreement (a plain rival, a fit to
            # static clutter, is found again on every frame, and the provisional start
            # waits for a second call anyway).
            rivals = (T_best, T2) if rival else ()
    if ok and not confirmed and opt.probe_single and chk.n_cameras == 1:
        ok, why, T2 = _probe(T_best, chk, _judging(views, chk), setup)
        rivals = () if T2 is None else (T_best, T2)
    held = pend.held if pend is not None else None
    if not ok and held is not None and opt.confirm_upheld and not why.startswith("ambiguous") and \
            _upheld(held, refined, again, mf, opt):
        res, rep = call.found(*held, "upheld", nh)
        return res, replace(rep, candidates=tuple(refined))
    plain = plain and ok  # passed every check, under the looser limits
    provisional = plain and opt.confirm_plain and not confirmed
    if provisional and not opt.provisional_start:
        ok, why = False, "plain faces: to be confirmed on the next call"
    if not ok:
        return call.none(nh, why, chk, candidates=tuple(refined), plain=plain, rivals=rivals)
    mode = "provisional" if provisional else "confirm" if plain and opt.confirm_plain else "search"
    res, rep = call.found(T_best, chk, mode, nh)
    return replace(res, provisional=provisional), replace(rep, candidates=tuple(refined), plain=plain)


def initialize(setup: InitSetup, frameset: FrameSet, seed_T_world_object: np.ndarray | None = None,
               rng: np.random.Generator | None = None, pending_T_world_object: np.ndarray | None = None,
               attempt: int = 0, pending_age_s: float = 0.0,
               recall: tuple = ()) -> tuple[InitResult | None, InitReport]:
    """Find the part in one frame set: a verified pose or None.

    A pure function of its inputs (the set-up is read-only; ``rng`` only
    perturbs the seeded starting points and defaults to a fixed seed).
    In stages: the pending pose refined again (:func:`_pending`), the seeded
    refinement (:func:`_seeded`), the search's hypotheses (:func:`_hypotheses`),
    their verification (:func:`_verified`) and the decision (:func:`_decided`).

    Parameters
    ----------
    setup : InitSetup
    frameset : FrameSet
    seed_T_world_object : ndarray, shape (4, 4), optional
        Predicted pose to try first (after a loss).
    rng : numpy Generator, optional
    pending_T_world_object : ndarray, shape (4, 4), optional
        A pose the previous call accepted only provisionally (its report's
        ``plain`` and first candidate): found again, refined from here or by
        the search, and still first among this call's candidates, the pose
        is returned (mode ``"confirm"``): its own refinement on this frame set
        where that passes (``InitOptions.confirm_own_refinement``), else the
        candidate found first.
    attempt : int
        Calls so far without a pose: selects the extra refinement window.
    pending_age_s : float
        Time from the pending pose's frame set to this one, s.
    recall : tuple of ndarray (4, 4)
        Poses an earlier call found ambiguous with each other (its report's
        ``rivals``): refined again here and counted among the candidates
        (``InitOptions.recall_rivals_s``).

    Returns
    -------
    result : InitResult or None
    report : InitReport
    """
    t0, c0 = time.perf_counter(), time.thread_time()
    rng = rng if rng is not None else np.random.default_rng(0)
    views = _views(setup, frameset)
    call = _Call(setup, views, t0, c0)
    if not views:
        return call.none(0, "no images")
    # A provisional pose from the previous call, refined again here: it joins
    # the search's candidates and is confirmed only if it still comes first
    # (a pose fitted to static clutter is found again on every frame; the
    # search may find the part this time).
    pend = _pending(setup, views, pending_T_world_object, pending_age_s) \
        if pending_T_world_object is not None else None
    if seed_T_world_object is not None:
        answer = _seeded(call, seed_T_world_object, rng)
        if answer is not None:
            return answer
    cand, nh = _hypotheses(setup, views, attempt)
    if not len(cand) and (pend is None or pend.passing is None):
        return call.none(nh, "no hypotheses")
    refined, again = _verified(setup, views, cand, attempt, pend, recall)
    if setup.options.workspace is not None:  # (a refinement can leave the volume)
        w, c = setup.options.workspace, setup.centre
        refined = [(T, k) for T, k in refined if centres_inside(T[:3, :3], T[:3, 3], c, w)[0]]
        again = [T for T in again if centres_inside(T[:3, :3], T[:3, 3], c, w)[0]]
    if not refined:
        return call.none(nh, "no candidate in the working volume")
    return _decided(call, refined, again, pend, nh)


class Initializer:
    """Callable initialiser for the tracker: ``initializer(frameset) -> InitResult | None``.

    Holds only the constant set-up, an optional seed (the predicted pose after
    a loss), a pose awaiting confirmation (accepted by one camera under the
    plain-face limits: returned as provisional, confirmed if a later call
    finds it again; the tracker keeps it current with
    :meth:`await_confirmation`), the poses of the last ambiguity found, for the
    calls of the next ``InitOptions.recall_rivals_s`` (cleared when a pose is
    returned) and the report of the last call (``last_report``, with its
    compute time).
    """

    def __init__(self, setup: InitSetup):
        self.setup = setup
        self._seed = None  # (T_world_object, velocity (6,) or None, t_ns)
        self._pending = None  # (T_world_object, t_ns) awaiting confirmation (plain-face limits)
        self._attempt = 0  # calls without a pose since the last one (or the last reseed)
        self._rivals = None  # (poses, t_ns): the last ambiguity found (InitOptions.recall_rivals_s)
        self.last_report: InitReport | None = None

    def reseed(self, T_world_object: np.ndarray, velocity: np.ndarray | None = None, t_ns: int | None = None) -> None:
        """Try near this pose first (the tracker's last good estimate).

        Parameters
        ----------
        T_world_object : ndarray, shape (4, 4)
        velocity : ndarray, shape (6,), optional
            ``[v (m/s, world), w (rad/s, world)]`` at ``t_ns``: the seed is
            propagated (constant velocity) to each frame set's stamp.
        t_ns : int, optional
            Stamp of that estimate.
        """
        T = np.asarray(T_world_object, float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"seed pose must be a finite (4, 4) array, got shape {T.shape}")
        v = None if velocity is None else np.asarray(velocity, float).reshape(6)
        self._seed = (T, v, t_ns)
        self._attempt = 0

    def await_confirmation(self, T_world_object: np.ndarray, t_ns: int) -> None:
        """The next call confirms this pose (the tracker's estimate of a provisional start)
        if it finds it again, first among its candidates (see ``pending_T_world_object``)."""
        self._pending = (np.asarray(T_world_object, float), t_ns)

    def clear_seed(self) -> None:
        self._seed = None
        self._pending = None
        self._rivals = None

    def predicted_seed(self, t_ns: int) -> np.ndarray | None:
        """The seed pose propagated to ``t_ns`` (None without a seed)."""
        if self._seed is None:
            return None
        T, v, ts = self._seed
        if v is None or ts is None:
            return T
        dt = (t_ns - ts) * 1e-9
        return transform_from_rt(exp_so3(v[3:] * dt) @ T[:3, :3], T[:3, 3] + v[:3] * dt)

    def warm_up(self) -> None:
        """Load the compiled kernels (:mod:`vespro.jit`, cached on disk) before the first call.

        A first call in a fresh process otherwise spends ~0.35 s of CPU loading
        them; the server's worker process calls this at start-up, before a
        frame arrives. Works on a blank image of the first camera in front of
        it; decides nothing.
        """
        setup = self.setup
        cam = setup.rig.cameras[0]
        img = np.zeros((cam.intrinsics.height, cam.intrinsics.width), np.uint8)
        feat = extract_features(cam.name, img, cam.intrinsics.K, setup.options.edges)
        T_wc = np.asarray(cam.T_world_camera, float) if cam.is_fixed else np.eye(4)
        T_co = np.eye(4)
        T_co[2, 3] = 4.0 * setup.mf.diameter
        T = T_wc @ T_co
        view = CameraView(feat, T_wc, cam.is_fixed)
        R = T_co[None, :3, :3].repeat(2, 0)
        t = T_co[None, :3, 3].repeat(2, 0)
        rank_in_camera(R, t, feat, setup.mf, tree=setup.tree)
        refine_pose(T, [view], setup.mf, setup.tree, rounds=1, max_nfev=1)
        refine_subpixel(T, [view], setup.mf, setup.tree, rounds=1, shared_edge_px=setup.options.shared_edge_px)

    def __call__(self, frameset: FrameSet) -> InitResult | None:
        seed = self.predicted_seed(frameset.t_ns)
        pend, age = (None, 0.0) if self._pending is None else (self._pending[0],
                                                               (frameset.t_ns - self._pending[1]) * 1e-9)
        recall = ()
        if self._rivals is not None:
            age_r = (frameset.t_ns - self._rivals[1]) * 1e-9
            if 0.0 <= age_r <= self.setup.options.recall_rivals_s:
                recall = self._rivals[0]
            else:
                self._rivals = None
        result, report = initialize(self.setup, frameset, seed, np.random.default_rng(frameset.index), pend,
                                    self._attempt, age, recall)
        self.last_report = report
        if report.rivals and self.setup.options.recall_rivals_s > 0:
            self._rivals = (report.rivals, frameset.t_ns)
        self._pending = (report.candidates[0][0], frameset.t_ns) if report.plain and (
            result is None or result.provisional) else None
        settled = result is not None and not result.provisional
        self._attempt = 0 if settled else self._attempt + 1
        if settled:
            self._seed = None
            self._rivals = None
        return result


def decision_options(decision: str, textured: bool = False) -> dict:
    """The :class:`InitOptions` fields the tracker's decision sets: with the bank (``"bank"``) the
    likelihood takes texture inside the faces as clutter, so the plain-face checks are off; with
    the rules, the faces are plain unless ``textured``."""
    return {"plain_faces": not (textured or decision == "bank")}


def make_initializer(rig: Rig, model: Model, options: InitOptions | None = None, **overrides) -> Initializer:
    """An initialiser for a rig and a model.

    Parameters
    ----------
    rig : Rig
    model : Model
    options : InitOptions, optional
    **overrides
        Fields of :class:`InitOptions` to change.

    Returns
    -------
    Initializer
        ``initializer(frameset) -> InitResult | None``; ``.reseed(T, velocity,
        t_ns)``; ``.last_report``.
    """
    from dataclasses import replace

    options = replace(options or InitOptions(), **overrides)
    return Initializer(make_setup(rig, model, options))
