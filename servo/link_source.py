"""The pose stream as the servo loop's sample source.

Adapts :class:`servo.receiver.PoseReceiver` (wire ``PoseMsg``) to the loop's
``SampleSource`` (``latest(now_ns) -> (TargetSample | None, age_ns)``).

Clocks: the vision PC stamps ``t_capture_ns`` on its own clock. The receiver
knows the age of a pose on ours (time since reception plus the sender's own
capture-to-send delay), so the sample's capture time on the servo clock is
``now - age`` at first sight; the line's transport delay (a few ms on a
serial line, see ``vespro.wire``) is the part not accounted for.
"""

from __future__ import annotations

from vespro.wire import PoseStatus

from .receiver import PoseReceiver
from .target import SampleStatus, TargetSample

__all__ = ["LinkSource"]

NO_SAMPLE_AGE = 2**63 - 1


class LinkSource:
    """Newest valid pose from the link, as a :class:`TargetSample`.

    Poses whose status is not TRACKING come through with status LOST (the
    loop treats them as no sample, so its watchdog runs).
    """

    def __init__(self, receiver: PoseReceiver, object_id: int | None = None):
        self.receiver = receiver
        self.object_id = object_id
        self._msg = None
        self._sample: TargetSample | None = None
        self.samples = 0  # poses handed to the loop (the loop counts those it used)

    def latest(self, now_ns: int) -> tuple[TargetSample | None, int]:
        self.receiver.poll(now_ns)
        msg, age = self.receiver.latest(now_ns, self.object_id)
        if msg is None:
            return None, NO_SAMPLE_AGE
        if msg is not self._msg:  # a new pose (the receiver has checked its order)
            self._msg = msg
            self.samples += 1
            self._sample = TargetSample(
                t_capture_ns=int(now_ns - age), p_world_object=msg.p_world_object,
                q_world_object=msg.q_world_object, v_world_object=msg.v_world_object,
                w_world_object=msg.w_world_object, cov=msg.cov,
                status=SampleStatus.OK if msg.status == PoseStatus.TRACKING else SampleStatus.LOST, seq=msg.seq,
            )
        return self._sample, age
