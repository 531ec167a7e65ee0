"""VESPRO control side: 500 Hz position-based visual servoing.

Imports from ``vespro`` only the wire protocol module (``vespro.wire``), and what
both sides' processes share from ``rtkit`` (its Rerun view's worker process, the
robot's shared-memory block).

Modules (dependencies point down the list):

- ``rotation``: quaternion (w, x, y, z) / rotation-vector helpers, in place.
- ``clock``: ``SimClock`` (lockstep) and ``WallClock`` (sleep, then spin).
- ``target``: ``TargetSample``, the object pose the loop consumes.
- ``kinematics``: FK and Jacobian of the TCP from ``models/arm.xml``, CLIK.
- ``planner``: jerk-limited tracking (Ruckig) with latency compensation and
  workspace clamp; trapezoidal point-to-point and via-point motions.
- ``safety``: ``Status``, stop policies, command checks, pose-stream watchdog.
- ``robot``: the ``Robot`` interface and ``MujocoArm``.
- ``loop``: ``step(state, sample, t_ns, out) -> Status`` and the ``Scheduler``.
- ``recorder``: preallocated time histories, saved as NPZ + CSV.
- ``virtual_target``: a sampled, delayed conveyor part for virtual mode.
- ``view``: the servo's series in a Rerun recording (``servo run --view-...``).
"""

__version__ = "0.1.0"
