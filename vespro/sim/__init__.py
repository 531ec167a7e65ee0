"""The simulated cell (MuJoCo): scene, motions, imaging and capture.

Importing this package sets ``MUJOCO_GL=egl`` unless already set (offscreen CPU
rendering through Mesa).
"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
