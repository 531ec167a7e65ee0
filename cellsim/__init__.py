"""The simulated cell: the plant that drives both sides and the whole-cell demo.

Above ``vespro`` and ``servo``: it imports both (and ``rtkit``); neither imports it
(``vespro demo`` is handed here by the ``vespro`` command line when it runs).

- ``plant``: the cell's physics in a process of its own (``python -m cellsim.plant``),
  the arm's drives on a shared-memory fieldbus, the world state for the cameras.
- ``demo``: plant, pose server and servo end to end, in real time or lockstep, scored
  against the plant's ground truth.
- ``cmd_demo``: ``vespro demo``'s run and its summary on the terminal.
"""

import vespro as _vespro  # noqa: F401  (first: it picks MuJoCo's offscreen rendering before mujoco loads)
