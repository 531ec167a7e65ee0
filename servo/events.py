"""The safety record: every stop, fault, late tick and rejected pose, counted by cause.

The loop writes into a :class:`SafetyRecord` on preallocated memory (counters
by cause, and a ring of the most recent events with the time, the value that
tripped and the limit it was checked against); ``servo run`` prints its
counters in the status line and writes :meth:`SafetyRecord.to_dict` into
``--stats-json``. Per tick, the loop's :class:`~servo.loop.Command` carries
the same facts (``flags``, ``reject``, ``trip_value``, ``trip_limit``) for the
recorder's time histories.

Event kinds
-----------
- ``stop``: a controlled stop began (decelerate within the planner's limits,
  drives stay on), cause: the check that fired (``WATCHDOG``, ``TIMING``,
  ``TCP_SPEED``, ``WORKSPACE``, ...);
- ``immediate_stop``: hold the last position, drives off (a check whose policy
  is IMMEDIATE);
- ``fault``: drives off, latched (non-finite command, broken clock, planner
  error);
- ``late_tick``: a tick later than the late-tick limit (counted; a stop only
  under the timing policy);
- ``reject``: a pose not used, cause: the reason (see :data:`REJECT_NAMES`);
- ``clamp``: the target left the planner's workspace and is held at its
  boundary (value: how far it was moved, m; recorded when it leaves, not per
  tick); no stop: the reference waits at the boundary.

Values and limits are in SI units (None where there is no number: a lost
pose, a non-finite command): seconds for the watchdog (time since the
last valid pose) and for timing (the tick's dt), m/s for the TCP speed, rad/s
for a joint velocity, rad for a joint position, m for the workspace (distance
outside the box), s for the age of a stale or future pose.
"""

from __future__ import annotations

import enum
import math

import numpy as np

from .safety import Check, Reject

__all__ = ["EventKind", "REJECT_NAMES", "SafetyRecord", "check_names"]


class EventKind(enum.IntEnum):
    STOP = 0
    IMMEDIATE_STOP = 1
    FAULT = 2
    LATE_TICK = 3
    REJECT = 4
    CLAMP = 5


#: Reasons the loop rejects a pose (``servo.safety.Reject``), as they appear in the record.
REJECT_NAMES = tuple(r.name.lower() for r in Reject if r != Reject.NONE)

_CHECKS = tuple(c for c in Check if c != Check.NONE)
_CHECK_BIT = {c: i for i, c in enumerate(_CHECKS)}


def _num(x) -> float | None:
    """A float for JSON (None for NaN: nothing was measured)."""
    x = float(x)
    return None if math.isnan(x) else x


def check_names(flags: int) -> list[str]:
    """Names of the ``Check`` bits set in ``flags``."""
    return [c.name for c in _CHECKS if flags & c]


class SafetyRecord:
    """Counters by cause and a ring of recent events (preallocated; no allocation per event).

    Parameters
    ----------
    capacity : int
        Recent events kept (the oldest is overwritten; counters are never lost).
    """

    def __init__(self, capacity: int = 256):
        self.capacity = int(capacity)
        self.t_ns = np.zeros(self.capacity, np.int64)
        self.kind = np.zeros(self.capacity, np.int8)
        self.cause = np.zeros(self.capacity, np.int32)
        self.value = np.zeros(self.capacity)
        self.limit = np.zeros(self.capacity)
        self.n_events = 0
        # counters[kind, cause]: causes are Check bits for stops/faults, Reject codes for rejects
        self.counts = np.zeros((len(EventKind), 32), np.int64)

    def clear(self) -> None:
        self.n_events = 0
        self.counts[:] = 0

    def add(self, t_ns: int, kind: EventKind, cause: int, value: float, limit: float) -> None:
        """Record one event. ``cause``: a single ``Check`` flag, or a ``Reject`` code."""
        idx = _CHECK_BIT[cause] if kind <= EventKind.FAULT else int(cause)
        self.counts[int(kind), idx] += 1
        j = self.n_events % self.capacity
        self.t_ns[j] = t_ns
        self.kind[j] = kind
        self.cause[j] = cause
        self.value[j] = value
        self.limit[j] = limit
        self.n_events += 1

    def count(self, kind: EventKind, cause: int | None = None) -> int:
        """Events of ``kind`` (of one cause, or all)."""
        row = self.counts[int(kind)]
        if cause is None:
            return int(row.sum())
        idx = _CHECK_BIT[Check(cause)] if kind <= EventKind.FAULT else int(cause)
        return int(row[idx])

    def by_cause(self, kind: EventKind) -> dict[str, int]:
        """Non-zero counts of ``kind`` by cause name."""
        row = self.counts[int(kind)]
        if kind == EventKind.REJECT:
            return {Reject(i).name.lower(): int(row[i]) for i in range(1, len(Reject)) if row[i]}
        if kind in (EventKind.LATE_TICK, EventKind.CLAMP):
            return {kind.name.lower(): int(row.sum())} if row.sum() else {}
        return {c.name: int(row[i]) for i, c in enumerate(_CHECKS) if row[i]}

    def recent(self) -> list[dict]:
        """The events still in the ring, oldest first, as plain data."""
        n = min(self.n_events, self.capacity)
        start = self.n_events - n
        out = []
        for k in range(start, self.n_events):
            j = k % self.capacity
            kind = EventKind(int(self.kind[j]))
            c = int(self.cause[j])
            if kind == EventKind.REJECT:
                cause = Reject(c).name.lower()
            elif kind in (EventKind.LATE_TICK, EventKind.CLAMP):
                cause = "workspace" if kind == EventKind.CLAMP else "late"
            else:
                cause = "|".join(check_names(c)) or "NONE"
            out.append({"t_s": round(int(self.t_ns[j]) * 1e-9, 6), "kind": kind.name.lower(), "cause": cause,
                        "value": _num(self.value[j]), "limit": _num(self.limit[j])})
        return out

    def to_dict(self) -> dict:
        """Counters by kind and cause, plus the recent events (``--stats-json``)."""
        return {
            "stops": self.by_cause(EventKind.STOP),
            "immediate_stops": self.by_cause(EventKind.IMMEDIATE_STOP),
            "faults": self.by_cause(EventKind.FAULT),
            "late_ticks": self.count(EventKind.LATE_TICK),
            "target_clamped": self.count(EventKind.CLAMP),
            "rejected": self.by_cause(EventKind.REJECT),
            "events_total": self.n_events,
            "recent_events": self.recent(),
        }

    def summary(self) -> str:
        """One short text for a status line: ``stops WATCHDOG:3 | rejected stale:2 | late 1``."""
        parts = []
        for label, kind in (("stops", EventKind.STOP), ("estops", EventKind.IMMEDIATE_STOP),
                            ("faults", EventKind.FAULT), ("rejected", EventKind.REJECT)):
            d = self.by_cause(kind)
            if d:
                parts.append(label + " " + ",".join(f"{k}:{v}" for k, v in d.items()))
        late = self.count(EventKind.LATE_TICK)
        if late:
            parts.append(f"late {late}")
        clamp = self.count(EventKind.CLAMP)
        if clamp:
            parts.append(f"clamped {clamp}")
        return " | ".join(parts) if parts else "no safety events"
