"""The imaging pipeline's pixel noise moves image features as documented."""

import cv2
import numpy as np
import pytest

from vespro.camera import CameraIntrinsics
from vespro.sim.imaging import ImageEffects, ImagePipeline


def _checker(h=480, w=640, sq=40):
    y, x = np.mgrid[0:h, 0:w]
    img = (((x // sq) + (y // sq)) % 2 * 160 + 40).astype(np.uint8)
    return np.dstack([img] * 3)


def test_pixel_noise_moves_corners_with_the_stated_std():
    intr = CameraIntrinsics.from_fovy(640, 480, 40)
    img = _checker()
    truth = np.array([[x - 0.5, y - 0.5] for x in range(80, 600, 40) for y in range(80, 440, 40)], np.float32)
    rng = np.random.default_rng(0)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4)

    def detect(pipeline):
        grey = cv2.cvtColor(pipeline.apply(img, rng), cv2.COLOR_BGR2GRAY)
        return cv2.cornerSubPix(grey, truth.reshape(-1, 1, 2).copy(), (5, 5), (-1, -1), crit).reshape(-1, 2)

    clean = detect(ImagePipeline(intr, intr))
    noisy = ImagePipeline(intr, intr, ImageEffects(noise_px=0.5))
    d = np.concatenate([detect(noisy) - clean for _ in range(4)])
    std = d.std(axis=0)
    # 4 x 117 corners: the sample std is within ~5% of the true one; allow 20% for the
    # refinement window averaging the (smooth) field over its 11x11 pixels.
    assert np.all(np.abs(std - 0.5) < 0.1), std
    assert np.all(np.abs(d.mean(axis=0)) < 0.06)
    # Independent between distant corners (the field's correlation length is 6 px).
    dx = d[:117, 0]
    assert abs(np.corrcoef(dx[:-1], dx[1:])[0, 1]) < 0.3


def test_sensor_noise_and_validation():
    intr = CameraIntrinsics.from_fovy(64, 48, 40)
    p = ImagePipeline(intr, intr, ImageEffects(intensity_noise=3.0))
    out = p.apply(np.full((48, 64, 3), 100, np.uint8), np.random.default_rng(1))
    assert abs(out.astype(float).std() - 3.0) < 0.4
    with pytest.raises(ValueError, match="random generator"):
        p.apply(np.zeros((48, 64, 3), np.uint8))
    with pytest.raises(ValueError, match="noise_px"):
        ImageEffects(noise_px=-1)


def test_mono_camera_gives_the_grey_of_the_colour_image():
    # Distortion (a real remap) and blur on: converting first must give the grey of the
    # colour pipeline's output, up to rounding (one grey level).
    intr = CameraIntrinsics.from_fovy(640, 480, 40)
    dist = CameraIntrinsics(intr.width, intr.height, intr.K, np.array([-0.2, 0.08, 0.0005, -0.0003, -0.01]))
    rgb = np.dstack([_checker()[..., 0], _checker(sq=30)[..., 0], _checker(sq=50)[..., 0]])
    fx = ImageEffects(blur_px=0.8)
    colour = ImagePipeline(dist, intr, fx).apply(rgb)
    mono = ImagePipeline(dist, intr, fx, mono=True).apply(rgb)
    assert colour.shape == (480, 640, 3) and mono.shape == (480, 640) and mono.dtype == np.uint8
    diff = np.abs(mono.astype(int) - cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY).astype(int))
    assert diff.max() <= 1, diff.max()
    # Noise works on one channel too.
    noisy = ImagePipeline(dist, intr, ImageEffects(noise_px=0.5, intensity_noise=2.0), mono=True)
    assert noisy.apply(rgb, np.random.default_rng(0)).shape == (480, 640)


@pytest.mark.parametrize("n", [2, 3])
def test_supersampled_pixel_is_the_mean_over_its_area(n):
    """With ``supersample`` n each pixel averages n x n render samples spread over
    its area. A render that is a quadratic function of the ray gives, per pixel,
    the function's mean over the pixel's footprint; independently computed here
    by integrating (dense midpoint rule) through vespro.camera's model."""
    from vespro.camera import undistort_pixels
    from vespro.sim.scene import render_intrinsics

    intr = CameraIntrinsics(160, 120, [[150.0, 0, 81.0], [0, 151.0, 58.5], [0, 0, 1]], [-0.2, 0.08, 0.0005, -0.0003, -0.01])
    render, _ = render_intrinsics(intr, supersample=n)
    assert render.fx == pytest.approx(n * max(intr.fx, intr.fy))
    # Grey level as a function of the normalised ray: curved enough that a sample
    # offset by a fraction of a pixel, or a missing average, changes the pixel.
    def grey(xn, yn):
        return 100.0 + 50.0 * xn - 30.0 * yn + 120.0 * xn * xn + 80.0 * xn * yn  # 40-195 over the image

    v, u = np.mgrid[0:render.height, 0:render.width].astype(float)
    img = grey((u - render.cx) / render.fx, (v - render.cy) / render.fy)
    pipe = ImagePipeline(intr, render, supersample=n)
    out = pipe.map_x.shape
    assert out == (n * 120, n * 160)
    res = cv2.remap(img.astype(np.float32), pipe.map_x, pipe.map_y, cv2.INTER_LINEAR)
    res = cv2.resize(res, (160, 120), interpolation=cv2.INTER_AREA)
    # Reference: the mean of grey over each pixel area, 8x8 midpoints.
    m = 8
    off = (np.arange(m) + 0.5) / m - 0.5
    us, vs = np.meshgrid((np.arange(160)[:, None] + off).ravel(), (np.arange(120)[:, None] + off).ravel())
    ideal = undistort_pixels(intr, np.stack([us.ravel(), vs.ravel()], 1))
    g = grey((ideal[:, 0] - intr.cx) / intr.fx, (ideal[:, 1] - intr.cy) / intr.fy).reshape(120 * m, 160 * m)
    ref = cv2.resize(g.astype(np.float32), (160, 120), interpolation=cv2.INTER_AREA)
    # Bilinear render lookup of a quadratic (~1e-3 levels) and n x n vs 8 x 8 midpoints
    # of a quadratic (< 0.01 levels here); a quarter-pixel sample offset gives ~0.1 levels.
    assert np.abs(res - ref).max() < 0.02, np.abs(res - ref).max()
    # The pipeline itself (8-bit) gives the same up to rounding (input and output, 0.5 each).
    rgb = np.clip(np.round(img), 0, 255).astype(np.uint8)
    got = pipe.apply(np.dstack([rgb] * 3))
    assert np.abs(got[..., 1].astype(float) - ref).max() < 1.1


@pytest.mark.parametrize("effects, mono", [
    (ImageEffects(noise_px=0.5, blur_px=0.6), True),   # the demo's cameras: warp, then blur
    (ImageEffects(noise_px=0.5), False),                 # the warp makes the image
    (ImageEffects(blur_px=0.6, intensity_noise=2.0), True),
    (ImageEffects(), False),                             # an exact image: the colour conversion makes it
])
def test_every_image_is_its_own_though_the_pipeline_reuses_its_buffers(effects, mono):
    """The pipeline keeps its intermediate images from frame to frame; the image it returns is
    new each time (a frame set is kept downstream while the next one is made), and equal to
    what a fresh pipeline makes from the same render and random state."""
    intr = CameraIntrinsics.from_fovy(640, 480, 40)
    renders = [_checker(), np.ascontiguousarray(_checker()[::-1])]
    reused = ImagePipeline(intr, intr, effects, mono=mono)
    rng = np.random.default_rng(3)
    first = reused.apply(renders[0], rng)
    kept = first.copy()
    second = reused.apply(renders[1], rng)
    assert not np.shares_memory(first, second)
    assert np.array_equal(first, kept)  # not overwritten by the next frame
    rng = np.random.default_rng(3)
    fresh = ImagePipeline(intr, intr, effects, mono=mono)
    fresh.apply(renders[0], rng)
    assert np.array_equal(second, ImagePipeline.apply(fresh, renders[1], rng))
    assert second.shape == ((480, 640) if mono else (480, 640, 3)) and second.dtype == np.uint8
