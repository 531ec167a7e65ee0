"""The robot as the loop sees it: read joints, command joints, stop.

:class:`Robot` is the interface; :class:`MujocoArm` is the simulated arm
(the MJCF of ``models/arm.xml`` with its position servos). A real arm is a new
class with the same methods (read, command, stop, enable; plant_step a no-op), not a new loop.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import mujoco
import numpy as np

from .kinematics import DEFAULT_ARM_XML

__all__ = ["Robot", "MujocoArm"]


@runtime_checkable
class Robot(Protocol):
    """What the scheduler needs from an arm (joint order as in the MJCF)."""

    n: int

    def read(self, q_out: np.ndarray) -> None:
        """Measured joint positions (n,), rad, into ``q_out``."""
        ...

    def command(self, q: np.ndarray, qd: np.ndarray) -> None:
        """Joint position command (n,), rad, with velocity feedforward (n,), rad/s."""
        ...

    def stop(self) -> None:
        """Drives off: brakes hold the arm where it is; commands are ignored until ``enable``."""
        ...

    def enable(self) -> None:
        """Drives on again (after a stop and a loop reset)."""
        ...

    def plant_step(self) -> None:
        """Advance a simulated plant by one tick (no-op on a real arm)."""
        ...


class MujocoArm:
    """The simulated arm: MuJoCo stepped at the model timestep (2 ms), one tick per call.

    The position actuators are PD drives (``kp``, ``kv`` from the MJCF). The
    velocity feedforward enters as a shift of the position command,
    ``ctrl = q + (kv + d) / kp * qd`` (d: joint damping), which turns the
    actuator force into ``kp (q - q_m) + kv (qd - qd_m)`` plus damping
    compensation: a drive with velocity feedforward, as industrial drives have.
    Without it a joint moving at ``qd`` lags by ``(kv + d) / kp * qd`` (50 ms
    worth of motion here).

    Parameters
    ----------
    model : path or MjModel
    q0 : (n,) initial joint positions, rad
    velocity_feedforward : bool
    ticks_per_step : int
        MuJoCo steps per ``plant_step`` (the tick is ``ticks_per_step * timestep``).
    contacts : bool
        Keep MuJoCo contacts. Off by default: ``models/arm.xml`` declares no
        ``<contact><exclude>`` pairs and its capsules interpenetrate (forearm /
        wrist_tube overlap by 2 cm at every pose; upper_arm / forearm touch
        when the elbow bends), so with contacts on, phantom self-collision
        forces of ~10 N m act on j3 and the arm drifts by millimetres from its
        command. The arm alone has nothing else to touch.
    """

    def __init__(
        self,
        model=DEFAULT_ARM_XML,
        q0=None,
        velocity_feedforward: bool = True,
        ticks_per_step: int = 1,
        contacts: bool = False,
    ):
        if not isinstance(model, mujoco.MjModel):
            model = mujoco.MjModel.from_xml_path(str(model))
        if not contacts:
            model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
        self.model = model
        self.data = mujoco.MjData(model)
        self.n = model.nu
        self.ticks_per_step = int(ticks_per_step)
        self.dt = model.opt.timestep * self.ticks_per_step
        # actuator -> joint (qpos address); position actuators: biasprm = [0, -kp, -kv]
        jid = model.actuator_trnid[:, 0]
        self._qadr = model.jnt_qposadr[jid].copy()
        self._vadr = model.jnt_dofadr[jid].copy()
        kp = -model.actuator_biasprm[:, 1]
        kv = -model.actuator_biasprm[:, 2]
        damp = model.dof_damping[self._vadr]
        self._ff = (kv + damp) / kp if velocity_feedforward else np.zeros(self.n)
        if q0 is not None:
            self.data.qpos[self._qadr] = q0
        mujoco.mj_forward(model, self.data)
        self.data.ctrl[:] = self.data.qpos[self._qadr]
        self.drives_on = True
        self._hold = np.zeros(self.n)
        self._ctrl = np.zeros(self.n)
        self.site_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "tool")

    def read(self, q_out: np.ndarray) -> None:
        q_out[:] = self.data.qpos[self._qadr]

    def command(self, q: np.ndarray, qd: np.ndarray) -> None:
        if not self.drives_on:
            return
        np.multiply(self._ff, qd, out=self._ctrl)
        self._ctrl += q
        self.data.ctrl[:] = self._ctrl

    def stop(self) -> None:
        if self.drives_on:
            # Simulated brakes: hold the measured position (ctrl = q, no feedforward).
            self._hold[:] = self.data.qpos[self._qadr]
            self.data.ctrl[:] = self._hold
            self.drives_on = False

    def enable(self) -> None:
        self.drives_on = True

    def plant_step(self) -> None:
        for _ in range(self.ticks_per_step):
            mujoco.mj_step(self.model, self.data)

    # -- simulation truth (tests, recording) --
    def tcp_position(self) -> np.ndarray:
        """Measured TCP position (3,), m, world (from the last step's kinematics)."""
        return self.data.site_xpos[self.site_id].copy()

    def tcp_matrix(self) -> np.ndarray:
        return self.data.site_xmat[self.site_id].reshape(3, 3).copy()
