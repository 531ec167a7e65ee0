"""The simulated cell (MuJoCo): scene, motions, imaging, capture, the world state the cameras render from.

Offscreen rendering uses Mesa EGL: ``vespro`` sets ``MUJOCO_GL=egl`` on import
unless the user chose otherwise.
"""
