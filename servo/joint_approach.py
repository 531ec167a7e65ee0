"""A joint-space approach for when the Cartesian one is blocked by a joint limit.

The Cartesian approach moves the tool along a straight line; from some starts
(an elbow or a wrist near its end stop, the arm wound the other way) that line
drives a joint into its limit, the CLIK brakes it there and the reference waits
for the arm, for ever. Then the loop plans this instead: the joints for the
approach target by IK from a few seeds (the current joints, and the arm's home
and ready poses), the nearest solution well inside the joint ranges, and a
synchronised joint trapezoid to it whose speed is scaled so that the tool
never moves faster than the planner's limit and never leaves the safety box
along the way (both checked on the path before it is used). At its end, at
rest, the Cartesian approach takes over from a configuration that can reach.

Planning runs once, outside the fast path (an IK of a few hundred small
iterations: a few milliseconds, i.e. one late tick when it happens on the wall
clock).
"""

from __future__ import annotations

import numpy as np

from .kinematics import ArmKinematics, solve_ik
from .planner import JointTrapezoid

__all__ = ["plan_joint_approach", "SEEDS"]

#: IK seeds besides the current joints: home, and a ready pose with the tool down in both wrist
#: configurations (the base joint of each is turned towards the goal).
SEEDS = (np.zeros(6), np.array([0.0, 0.3, -0.3, 0.0, 1.57, 0.0]), np.array([0.0, 0.3, -0.3, np.pi, -1.57, np.pi]))


def plan_joint_approach(kin: ArmKinematics, q: np.ndarray, T_goal: np.ndarray, qd_max, qdd_max,
                        tcp_speed_max: float, box_min, box_max, margin_rad: float = 0.05,
                        n_check: int = 24) -> JointTrapezoid | None:
    """A joint motion from ``q`` to an IK solution of ``T_goal``, or None if none is safe.

    Parameters
    ----------
    kin : ArmKinematics
        Used for the IK and the path checks (its state is changed).
    q : (n,) rad
        Start (current joint command).
    T_goal : (4, 4)
        Tool pose to reach, world frame.
    qd_max, qdd_max : (n,) rad/s, rad/s^2
        Joint limits of the motion (before the tool speed scaling).
    tcp_speed_max : m/s
        The tool's speed along the path stays below this.
    box_min, box_max : (3,) m
        The tool stays inside this box (the safety workspace) along the path.
    margin_rad : rad
        The goal keeps this far from every joint limit.
    """
    lo = kin.q_min + margin_rad
    hi = kin.q_max - margin_rad
    best = None
    toward = float(np.arctan2(T_goal[1, 3], T_goal[0, 3]))
    for seed in (q, *SEEDS):
        if seed is not q:
            seed = seed.copy()
            seed[0] = toward
        qg, ok = solve_ik(kin, T_goal, seed)
        if not ok or np.any(qg < lo) or np.any(qg > hi):
            continue
        d = float(np.max(np.abs(qg - q) / np.asarray(qd_max, float)))
        if best is None or d < best[0]:
            best = (d, qg)
    if best is None:
        return None
    qg = best[1]
    dq = qg - q
    # Tool speed along the straight joint path: |J(q(s)) dq| ds/dt; check the box on the way.
    gain = 0.0
    for s in np.linspace(0.0, 1.0, n_check):
        kin.update(q + s * dq)
        if np.any(kin.p < box_min) or np.any(kin.p > box_max):
            return None
        gain = max(gain, float(np.linalg.norm(kin.J[:3] @ dq)))
    qd = np.asarray(qd_max, float)
    qdd = np.asarray(qdd_max, float)
    motion = JointTrapezoid(q, qg, qd, qdd)
    if motion.profile is None or gain == 0.0:
        return motion
    # ds/dt peaks at v_peak; scale the joint limits so that gain * v_peak <= 0.9 * tcp_speed_max
    # (margin: the path between the checked samples). Velocities by k and accelerations by k^2
    # scale v_peak by k whether the profile is a trapezoid or a triangle.
    k = min(1.0, 0.9 * tcp_speed_max / (gain * motion.profile.v_peak))
    if k < 1.0:
        motion = JointTrapezoid(q, qg, qd * k, qdd * (k * k))
    return motion
