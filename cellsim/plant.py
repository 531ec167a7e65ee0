"""The cell as a running plant: its own process, physics at 500 Hz in real time.

This is the simulated world of the demo. It steps the cell (arm drives and the
part on the conveyor) on the wall clock and exposes two shared-memory blocks:

- the robot "fieldbus" (:class:`servo.shm_robot.RobotShm`): measured joints out,
  joint commands in, as a real arm's controller would; the servo process drives
  the arm through it exactly as it drives the in-process MuJoCo arm;
- the world state (:class:`vespro.sim.world.WorldShm`): arm joints and the object's pose, which
  the vision process renders its camera images from (the cameras "see" the world).

The drive model is the servo's own :class:`servo.robot.MujocoArm` on the cell
model (one drive model, not two). The ground truth (object pose, TCP pose,
joints, at every step) goes into a preallocated log written at the end, for
evaluators only.

Run as ``python -m cellsim.plant --help``.
"""

from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path

import mujoco
import numpy as np

from vespro.sim.world import WorldShm

__all__ = ["Plant", "run_plant"]


class Plant:
    """The cell's physics, one 2 ms step at a time (real-time and lockstep alike).

    Parameters
    ----------
    robot_shm, world_shm : str
        Names of existing shared-memory blocks (created by the demo).
    object_mesh : Path
    motion : vespro.sim.motion.Motion
        The part's trajectory (typically a Conveyor with a stop time).
    duration_s : float
        Sizes the preallocated ground-truth log.
    """

    def __init__(self, robot_shm: str, world_shm: str, object_mesh: Path, motion, duration_s: float,
                 q0: np.ndarray | None = None):
        from servo.robot import MujocoArm
        from servo.shm_robot import RobotShm

        from vespro.rig import Rig
        from vespro.sim.scene import SceneSpec, build_cell

        model, _ = build_cell(SceneSpec(Path(object_mesh), Rig(())))
        self.model = model
        # The arm starts at rest at q0 (the cell's "home" keyframe unless given).
        self.arm = MujocoArm(model, q0=np.array(model.key("home").qpos[:6] if q0 is None else q0, dtype=float))
        self.data = self.arm.data
        self.motion = motion
        self._obj = model.body("object").mocapid[0]
        self._tool = model.site("tool").id
        self.robot = RobotShm(robot_shm)
        self.world = WorldShm(world_shm)
        self.dt_ns = int(round(model.opt.timestep * 1e9))
        n_log = int(round(duration_s / model.opt.timestep)) + 2
        self.log = {"t_ns": np.zeros(n_log, np.int64), "q": np.zeros((n_log, 6)), "object": np.zeros((n_log, 7)),
                    "tcp": np.zeros((n_log, 7)), "drives_on": np.zeros(n_log, np.int8)}
        self.k = 0
        self._R_obj = self._q_obj = None  # the part's last rotation and its quaternion
        self.t0_ns = None
        self._cmd = np.zeros(2 + 12)
        self._q = np.zeros(6)
        self._have_cmd = False
        self._drives = True

    def start(self, t0_ns: int) -> None:
        """Publish the initial state, then declare the plant alive (readers never see zeros)."""
        from vespro.se3 import pq_from_transform

        self.t0_ns = int(t0_ns)
        self.arm.read(self._q)
        self.robot.write_state(self.t0_ns, self._q, self.data.qvel[:6])
        self.world.write(self.t0_ns, self._q, pq_from_transform(self.motion.pose(0.0)), 0)
        self.world.a[15] = float(t0_ns)
        self.world.a[16] = 1.0
        self.robot.set_alive(True)

    def step(self) -> int:
        """Apply the latest command, step physics, publish state; returns the new time, ns."""
        from vespro.se3 import quat_from_matrix

        arm, d, cmd = self.arm, self.data, self._cmd
        if self.robot.read_command(cmd):
            self._have_cmd = True
            if cmd[-1] > 0.5:
                if not arm.drives_on:
                    arm.enable()
                arm.command(cmd[1:7], cmd[7:13])
                self._drives = True
            elif self._drives:
                arm.stop()
                self._drives = False
        elif not self._have_cmd:
            arm.stop()  # hold until the servo speaks
        # A rotation converted only when it changed (a part on the belt keeps its own): SciPy's
        # conversion costs ~80 us a call, MuJoCo's step ~15 us.
        T_obj = self.motion.pose(self.k * self.dt_ns * 1e-9)
        if self._R_obj is None or not np.array_equal(T_obj[:3, :3], self._R_obj):
            self._R_obj = T_obj[:3, :3].copy()
            self._q_obj = quat_from_matrix(self._R_obj)
        pq = np.concatenate([T_obj[:3, 3], self._q_obj])
        d.mocap_pos[self._obj] = pq[:3]
        d.mocap_quat[self._obj] = pq[3:]
        arm.plant_step()
        arm.read(self._q)
        t_now = self.t0_ns + (self.k + 1) * self.dt_ns
        self.robot.write_state(t_now, self._q, d.qvel[:6])
        self.world.write(t_now, self._q, pq, self.k + 1)
        i = self.k
        if i < len(self.log["t_ns"]):
            lg = self.log
            lg["t_ns"][i] = t_now
            lg["q"][i] = self._q
            lg["object"][i] = pq
            lg["tcp"][i, :3] = d.site_xpos[self._tool]
            q = lg["tcp"][i, 3:]
            mujoco.mju_mat2Quat(q, d.site_xmat[self._tool])
            if q[0] < 0.0:
                q *= -1.0  # w >= 0, as vespro.se3 writes quaternions
            lg["drives_on"][i] = self._drives
        self.k += 1
        return t_now

    def finish(self, log_path: Path) -> None:
        """Mark the world stopped, save the ground-truth log, detach."""
        self.world.a[16] = 0.0
        self.robot.set_alive(False)
        log_path = Path(log_path)
        log_path.parent.mkdir(parents=True, exist_ok=True)
        n = min(self.k, len(self.log["t_ns"]))
        np.savez(log_path, **{k: v[:n] for k, v in self.log.items()})
        self.robot.close()
        self.world.close()


def run_plant(robot_shm: str, world_shm: str, object_mesh: Path, motion, duration_s: float, log_path: Path,
              realtime: bool = True, q0: np.ndarray | None = None) -> dict:
    """Step the cell in real time until ``duration_s`` (or SIGTERM/SIGINT); returns timing statistics."""
    from vespro.clock import WallClock

    plant = Plant(robot_shm, world_shm, object_mesh, motion, duration_s, q0=q0)
    n_steps = int(round(duration_s * 1e9 / plant.dt_ns))
    stop = {"now": False}

    def _stop(signum, frame):
        stop["now"] = True

    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, _stop)
    # No final spin: each step is stamped t0 + k dt whatever the wake-up, and a spinning plant
    # took a tenth of the core it shares with the servo and the start worker.
    clock = WallClock(spin_ns=0)
    t0 = clock.now_ns()
    plant.start(t0)
    late = []
    try:
        for k in range(n_steps):
            if stop["now"]:
                break
            t_k = t0 + k * plant.dt_ns
            if realtime:
                late.append(clock.sleep_until(t_k) - t_k)
            plant.step()
    finally:
        plant.finish(log_path)
    late = np.array(late, dtype=float) if late else np.zeros(1)
    return {"steps": plant.k, "late_us_median": float(np.median(late) * 1e-3),
            "late_us_p99": float(np.percentile(late, 99) * 1e-3)}


def main(argv=None) -> int:
    from vespro.library import object_mesh_path
    from vespro.sim.motion import Conveyor

    p = argparse.ArgumentParser(prog="python -m cellsim.plant", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robot-shm", required=True)
    p.add_argument("--world-shm", required=True)
    p.add_argument("--object", default="bracket")
    p.add_argument("--duration", type=float, default=40.0)
    p.add_argument("--speed", type=float, default=0.05, help="belt speed, m/s")
    p.add_argument("--y0", type=float, default=-0.35, help="part position along the belt at t = 0, m")
    p.add_argument("--stop-time", type=float, default=12.0, help="the belt starts stopping at this time, s")
    p.add_argument("--log", type=Path, required=True)
    p.add_argument("--lockstep", action="store_true", help="as fast as possible (no real-time pacing)")
    p.add_argument("--q0", help="the arm's starting joints, six comma-separated angles (rad); default: home")
    p.add_argument("--cpu", type=int, metavar="N", help="pin the plant to core N")
    p.add_argument("--fifo", type=int, default=0, metavar="PRIO", help="run SCHED_FIFO at this priority (0: normal)")
    args = p.parse_args(argv)
    from vespro.realtime import enter_realtime

    for msg in enter_realtime(args.cpu, 0, args.fifo):
        print(f"plant: {msg}", file=sys.stderr, flush=True)
    motion = Conveyor(speed=args.speed, y0=args.y0, stop_time=args.stop_time)
    q0 = None
    if args.q0:
        try:
            q0 = np.array([float(v) for v in args.q0.split(",")])
        except ValueError:
            q0 = np.zeros(0)
        if q0.shape != (6,) or not np.all(np.isfinite(q0)):
            p.error(f"--q0: six finite angles expected, got {args.q0!r}")
    stats = run_plant(args.robot_shm, args.world_shm, object_mesh_path(args.object), motion, args.duration,
                      args.log, realtime=not args.lockstep, q0=q0)
    print(f"plant: {stats['steps']} steps, wake-up lateness median {stats['late_us_median']:.1f} us "
          f"p99 {stats['late_us_p99']:.1f} us", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
