"""The sub-pixel edge fit (vespro.edgefit.refine_subpixel) on the gradient the edge aid hands it.

A simulator frame (one camera); ground truth only to place the starting pose.
"""

from types import SimpleNamespace

import numpy as np
from trial_frames import trial_frames

import vespro.edgeaid
from vespro.bsp import load_or_build_bsp
from vespro.edgeaid import EdgeAid
from vespro.edgefit import CameraView, refine_subpixel
from vespro.imageedges import image_gradient
from vespro.init.modelfeat import model_features
from vespro.se3 import exp_so3, transform_from_rt


def test_the_search_reads_a_float64_gradient_as_its_int16_sobel_values(monkeypatch):
    """The edge aid hands the fit its Sobel gradient as float64 (the compiled search reads
    that faster than int16): from a start 1 deg and 2 mm off, the two-round fit with the
    edge aid's settings is the fit on the int16 gradient to the bit (pose, normal matrix,
    counts, weights, contrasts); the gradient scaled by 1/8 (as some Sobel conventions
    have it) is not. The edge aid hands it float64."""
    rig, model, frames = trial_frames("bracket", 3, 1)
    fs, T_true = frames[0]
    cam = rig.cameras[0]
    dx, dy = image_gradient(fs.images[cam.name], 0.8)
    mf = model_features(model)
    tree = load_or_build_bsp(model)
    T0 = transform_from_rt(exp_so3([0.0, np.deg2rad(1.0), 0.0]) @ T_true[:3, :3], T_true[:3, 3] + [0.002, 0.0, 0.0])
    kw = dict(rounds=2, spacing_px=2.0, edge_outlier_px=1.0, near_peak_frac=0.6, info=True)

    def fit(grad):
        view = CameraView(SimpleNamespace(K=np.asarray(cam.intrinsics.K, float), grad=grad), cam.T_world_camera)
        return refine_subpixel(T0, [view], mf, tree, **kw)

    g16 = np.stack([dx, dy])
    assert g16.dtype == np.int16
    (Ta, fa), (Tb, fb) = fit(g16), fit(g16.astype(np.float64))
    assert fa is not None and fa.n_samples > 100 and not np.array_equal(Ta, T0)
    assert np.array_equal(Ta, Tb)
    assert np.array_equal(fa.normal, fb.normal) and np.array_equal(fa.offset_gram, fb.offset_gram)
    assert (fa.n_samples, fa.n_edges, fa.n_searched) == (fb.n_samples, fb.n_edges, fb.n_searched)
    assert (fa.rms_px, fa.weight, fa.found_weight, fa.searched_weight) == \
        (fb.rms_px, fb.weight, fb.found_weight, fb.searched_weight)
    assert all(np.array_equal(a, b, equal_nan=True) for a, b in zip(fa.sample_contrast, fb.sample_contrast))
    Tc, _ = fit(g16.astype(np.float64) / 8.0)
    assert not np.array_equal(Ta, Tc)
    # What the edge aid hands the fit.
    seen = []
    monkeypatch.setattr(vespro.edgeaid, "refine_subpixel",
                        lambda T, views, *a, **k: seen.append(views[0].feat.grad.dtype) or refine_subpixel(T, views, *a, **k))
    assert EdgeAid(rig, model).measure(cam.name, fs.images[cam.name], cam.T_world_camera, T0) is not None
    assert seen == [np.float64]
