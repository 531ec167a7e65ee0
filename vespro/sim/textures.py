"""Small procedural grey textures for simulated clutter and textured parts.

A texture is a seeded pattern of random grey rectangles and strokes on a grey
ground (an edge-rich surface: printed cartons, stickers, machined marks),
small (64 x 64 texels by default) because a CPU rasteriser pays for every
textured pixel it samples. :func:`add_texture` puts one into an ``MjSpec``
with a material that tiles it ``per_metre`` times a metre on every face.
"""

from __future__ import annotations

import mujoco
import numpy as np

__all__ = ["grey_pattern", "add_texture"]


def grey_pattern(rng: np.random.Generator, size: int = 64, mean: float = 0.5, spread: float = 0.35,
                 n_marks: int = 14) -> np.ndarray:
    """A ``(size, size, 3)`` uint8 grey pattern: a ground and ``n_marks`` rectangles or strokes.

    Greys are drawn in ``mean +- spread`` (fractions of white), clipped to [0, 1].
    """
    def grey():
        return float(np.clip(mean + rng.uniform(-spread, spread), 0.0, 1.0))

    img = np.full((size, size), grey())
    for _ in range(n_marks):
        if rng.random() < 0.7:  # a rectangle
            w, h = rng.integers(size // 10, size // 2, 2)
        else:  # a stroke, horizontal or vertical
            w, h = (rng.integers(size // 3, size), rng.integers(1, 4))
            if rng.random() < 0.5:
                w, h = h, w
        x, y = rng.integers(0, size, 2)
        img[y:y + h, x:x + w] = grey()
    return np.repeat(np.round(255 * img).astype(np.uint8)[..., None], 3, axis=2)


def add_texture(s: mujoco.MjSpec, name: str, pixels: np.ndarray, per_metre: float) -> str:
    """Add a 2D texture and a material tiling it ``per_metre`` times a metre; returns the material name."""
    h, w = pixels.shape[:2]
    tex = s.add_texture(name=f"{name}_tex", type=mujoco.mjtTexture.mjTEXTURE_2D, width=w, height=h, nchannel=3)
    tex.data = np.ascontiguousarray(pixels, dtype=np.uint8).tobytes()
    mat = s.add_material(name=f"{name}_mat")
    mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = f"{name}_tex"
    mat.texuniform = True
    mat.texrepeat = [per_metre, per_metre]
    mat.specular = 0.1
    mat.shininess = 0.1
    mat.reflectance = 0.0
    return f"{name}_mat"


def planar_uv_mesh(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A mesh file with texture coordinates: every face projected on the plane of its dominant axis.

    Returns
    -------
    vertices : ndarray (3F, 3)
        One copy of its corners per face (faces do not share texture coordinates), m.
    faces : ndarray (F, 3) int
    uv : ndarray (3F, 2)
        Texture coordinates in metres (a material tiles them ``per_metre`` times).
    """
    import trimesh

    m = trimesh.load(str(path), force="mesh")
    v = m.vertices[m.faces].reshape(-1, 3)
    axis = np.argmax(np.abs(m.face_normals), axis=1).repeat(3)
    keep = np.array([[1, 2], [0, 2], [0, 1]])[axis]
    uv = np.take_along_axis(v, keep, axis=1)
    return v, np.arange(v.shape[0]).reshape(-1, 3), uv
