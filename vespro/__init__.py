"""VESPRO: vision-based 6-DoF pose estimation for robot cells.

Data flows one way: capture -> model/visibility -> tracker -> server -> link -> servo.
"""

import os as _os

# MuJoCo picks its OpenGL platform when first imported (the servo side imports it
# too): offscreen CPU rendering through Mesa EGL unless the user chose otherwise.
_os.environ.setdefault("MUJOCO_GL", "egl")

__version__ = "0.1.0"
