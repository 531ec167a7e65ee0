"""From a MuJoCo render to the image a real camera of the rig would deliver.

MuJoCo renders an ideal centred pinhole (:func:`vespro.sim.scene.render_intrinsics`).
:class:`ImagePipeline` turns it into the rig camera's image:

1. geometry: every output pixel samples the render where its ray hits, using the
   rig camera's matrix and plumb_bob distortion (one ``cv2.remap``); with
   ``supersample`` = n > 1 the render is n times finer, each output pixel is
   sampled at n x n points spread over its area and their mean is the pixel
   (a sensor integrates light over the pixel; box filter, ``cv2.INTER_AREA``);
2. pixel noise ``noise_px``: a random, smooth displacement field (new each frame)
   with standard deviation ``noise_px`` per axis and a correlation length of a
   few pixels, folded into the same remap. Image features (corners) move by it
   almost rigidly within their neighbourhood while distant features move
   independently: the "Gaussian pixel noise" of a feature detector, made in the
   image rather than added to detections, so detectors see it;
3. optional Gaussian blur (``blur_px``, sigma in pixels) and sensor noise
   (``intensity_noise``, sigma in grey levels).

Output is 8-bit BGR, as OpenCV and the recording format expect.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..camera import CameraIntrinsics, undistort_pixels
from ..memory import ScratchImages

__all__ = ["ImageEffects", "ImagePipeline"]

#: Displacement fields drawn per camera at start-up (each frame crops one).
FIELD_BANK = 8


@dataclass(frozen=True)
class ImageEffects:
    """Image degradations; all zero means an exact pinhole/distortion image.

    Attributes
    ----------
    noise_px : float
        Std of the geometric pixel noise per axis, px.
    noise_corr_px : float
        Correlation length (Gaussian sigma) of the displacement field, px.
    blur_px : float
        Gaussian blur sigma, px (0: none).
    intensity_noise : float
        Std of additive sensor noise, grey levels (0: none).
    """

    noise_px: float = 0.0
    noise_corr_px: float = 6.0
    blur_px: float = 0.0
    intensity_noise: float = 0.0

    def __post_init__(self):
        for k in ("noise_px", "noise_corr_px", "blur_px", "intensity_noise"):
            v = getattr(self, k)
            if not np.isfinite(v) or v < 0:
                raise ValueError(f"{k} must be a finite number >= 0, got {v}")


class ImagePipeline:
    """Per-camera post-processing of rendered frames.

    Parameters
    ----------
    intr : CameraIntrinsics
        The rig camera.
    render : CameraIntrinsics
        The centred pinhole MuJoCo renders for it.
    effects : ImageEffects
    mono : bool
        A monochrome camera: 8-bit grey images (what the tracker uses; a third
        of the pixels to remap, blur and write).
    supersample : int
        Samples per pixel and axis (``render`` must then be that much finer,
        :func:`vespro.sim.scene.render_intrinsics`).
    """

    def __init__(self, intr: CameraIntrinsics, render: CameraIntrinsics, effects: ImageEffects = ImageEffects(),
                 mono: bool = False, supersample: int = 1):
        self.intr = intr
        self.render = render
        self.effects = effects
        self.mono = bool(mono)
        self.supersample = n = int(supersample)
        if n < 1:
            raise ValueError(f"supersample must be an integer >= 1, got {supersample}")
        self._bank = None
        self._fields = None
        self._scratch = ScratchImages()  # intermediate images; only the returned image is new
        self.identity = n == 1 and (intr is render or (
            intr.width == render.width and intr.height == render.height
            and np.allclose(intr.K, render.K) and not intr.has_distortion
        ))
        if self.identity:
            u, v = np.meshgrid(np.arange(intr.width, dtype=np.float32), np.arange(intr.height, dtype=np.float32))
            self.map_x, self.map_y = u, v
        else:
            # Sample j of n along an axis of pixel u sits at u + (j + 0.5) / n - 0.5
            # (pixel centres at integers, the pixel spans u +- 0.5).
            off = (np.arange(n) + 0.5) / n - 0.5
            us = (np.arange(intr.width)[:, None] + off).ravel()
            vs = (np.arange(intr.height)[:, None] + off).ravel()
            u, v = np.meshgrid(us, vs)
            uv = np.stack([u.ravel(), v.ravel()], axis=1)
            ideal = undistort_pixels(intr, uv)  # ideal pixels of the rig camera matrix
            xn = (ideal[:, 0] - intr.cx) / intr.fx
            yn = (ideal[:, 1] - intr.cy) / intr.fy
            shape = (n * intr.height, n * intr.width)
            self.map_x = (render.fx * xn + render.cx).reshape(shape).astype(np.float32)
            self.map_y = (render.fy * yn + render.cy).reshape(shape).astype(np.float32)

    def _displacement(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """A displacement field for one frame, its x and y planes: a random crop of a bank of fields.

        Drawing a fresh field costs more than the render; a bank of
        ``FIELD_BANK`` fields drawn once, cropped at a random offset each frame,
        keeps every frame's statistics exact and frames independent wherever the
        crops are more than a correlation length apart.
        """
        h, w = self.intr.height, self.intr.width
        pad = 64
        if self._fields is None:
            # Each field's two planes stored apart: a crop of one is read in place, not copied.
            self._fields = [tuple(np.ascontiguousarray(f[..., i]) for i in range(2))
                            for f in (self._draw_field(rng, h + pad, w + pad) for _ in range(FIELD_BANK))]
        fx, fy = self._fields[int(rng.integers(0, FIELD_BANK))]
        dy, dx = rng.integers(0, pad, size=2)
        return fx[dy:dy + h, dx:dx + w], fy[dy:dy + h, dx:dx + w]

    def _draw_field(self, rng: np.random.Generator, h: int, w: int) -> np.ndarray:
        # The field is smooth over noise_corr_px, so it is drawn on a coarse grid
        # (half the correlation length per cell) and upsampled: ~1/9 of the
        # random numbers and blur work of a full-resolution draw.
        e = self.effects
        step = max(1, int(e.noise_corr_px // 2))
        hc, wc = -(-h // step) + 2, -(-w // step) + 2
        field = rng.standard_normal((hc, wc, 2), dtype=np.float32)
        field = cv2.GaussianBlur(field, (0, 0), e.noise_corr_px / step, borderType=cv2.BORDER_REFLECT)
        field = cv2.resize(field, (wc * step, hc * step), interpolation=cv2.INTER_LINEAR)[:h, :w]
        std = field[::4, ::4].reshape(-1, 2).std(axis=0)
        return field * (e.noise_px / np.maximum(std, 1e-12)).astype(np.float32)

    def _sensor_noise(self, rng: np.random.Generator, shape) -> np.ndarray:
        # A bank of Gaussian noise drawn once, cropped at a random offset per frame:
        # per-pixel statistics are exact and a frame costs a view, not 10^6 draws.
        pad = 64
        if self._bank is None or self._bank.shape[1:3] != (shape[0] + pad, shape[1] + pad):
            bank_shape = (2, shape[0] + pad, shape[1] + pad) + tuple(shape[2:])
            self._bank = np.round(rng.normal(0.0, self.effects.intensity_noise, bank_shape)).astype(np.int16)
        k, dy, dx = rng.integers(0, 2), rng.integers(0, pad), rng.integers(0, pad)
        return self._bank[k, dy:dy + shape[0], dx:dx + shape[1]]

    def apply(self, render_rgb: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """Rig-camera image from a MuJoCo render.

        Parameters
        ----------
        render_rgb : ndarray, shape (H_r, W_r, 3), uint8
            MuJoCo's RGB render at the ``render`` intrinsics.
        rng : numpy Generator, optional
            Needed when any noise is on.

        Returns
        -------
        ndarray, shape (H, W, 3), uint8, BGR; shape (H, W) grey for a mono camera
            (converted first, so the remap, blur and noise work on one channel)
        """
        e = self.effects
        noisy = e.noise_px > 0 or e.intensity_noise > 0
        if noisy and rng is None:
            raise ValueError("image noise needs a random generator")
        n = self.supersample
        # An image that a later step replaces goes into a reused buffer; the last one made is new.
        after_warp = n > 1 or e.blur_px > 0 or e.intensity_noise > 0
        later = after_warp or e.noise_px > 0 or not self.identity
        code = cv2.COLOR_RGB2GRAY if self.mono else cv2.COLOR_RGB2BGR
        shape = render_rgb.shape[:2] if self.mono else render_rgb.shape
        bgr = cv2.cvtColor(render_rgb, code, dst=self._scratch.get("colour", shape, np.uint8) if later else None)
        out_shape = self.map_x.shape + bgr.shape[2:]
        remap_dst = self._scratch.get("warped", out_shape, np.uint8) if after_warp else None
        if e.noise_px > 0:
            d = self._displacement(rng)
            if n > 1:
                # The field is in rig pixels; render pixels are n times finer.
                size = (self.map_x.shape[1], self.map_x.shape[0])
                d = tuple(n * cv2.resize(c, size, interpolation=cv2.INTER_LINEAR) for c in d)
            mx = np.add(self.map_x, d[0], out=self._scratch.get("map_x", self.map_x.shape, np.float32))
            my = np.add(self.map_y, d[1], out=self._scratch.get("map_y", self.map_y.shape, np.float32))
            out = cv2.remap(bgr, mx, my, cv2.INTER_LINEAR, dst=remap_dst, borderMode=cv2.BORDER_REPLICATE)
        elif not self.identity:
            out = cv2.remap(bgr, self.map_x, self.map_y, cv2.INTER_LINEAR, dst=remap_dst,
                            borderMode=cv2.BORDER_REPLICATE)
        else:
            out = bgr
        if n > 1:
            out = cv2.resize(out, (self.intr.width, self.intr.height), interpolation=cv2.INTER_AREA)
        if e.blur_px > 0:
            out = cv2.GaussianBlur(out, (0, 0), e.blur_px)
        if e.intensity_noise > 0:
            n = self._sensor_noise(rng, out.shape)
            out = cv2.add(out.astype(np.int16), n, dtype=cv2.CV_16S)
            out = np.clip(out, 0, 255).astype(np.uint8)
        return out
