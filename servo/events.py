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
- ``joint_approach``: the Cartesian approach was held at a joint limit and
  a joint-space approach was planned (value: its duration, s; None when no
  safe one was found and the arm keeps waiting);
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
    JOINT_APPROACH = 6


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


class _Ring:
    """The last ``capacity`` events of some kinds (preallocated arrays)."""

    def __init__(self, capacity: int):
        self.capacity = int(capacity)
        self.t_ns = np.zeros(self.capacity, np.int64)
        self.kind = np.zeros(self.capacity, np.int8)
        self.cause = np.zeros(self.capacity, np.int32)
        self.value = np.zeros(self.capacity)
        self.limit = np.zeros(self.capacity)
        self.n = 0  # events ever added

    def add(self, t_ns: int, kind: int, cause: int, value: float, limit: float) -> None:
        j = self.n % self.capacity
        self.t_ns[j] = t_ns
        self.kind[j] = kind
        self.cause[j] = cause
        self.value[j] = value
        self.limit[j] = limit
        self.n += 1

    def since(self, k: int) -> list[dict]:
        out = []
        for i in range(max(int(k), self.n - self.capacity), self.n):
            j = i % self.capacity
            kind = EventKind(int(self.kind[j]))
            c = int(self.cause[j])
            if kind == EventKind.REJECT:
                cause = Reject(c).name.lower()
            elif kind == EventKind.LATE_TICK:
                cause = "late"
            elif kind == EventKind.CLAMP:
                cause = "workspace"
            elif kind == EventKind.JOINT_APPROACH:
                cause = "joint_limit"
            else:
                cause = "|".join(check_names(c)) or "NONE"
            out.append({"t_s": round(int(self.t_ns[j]) * 1e-9, 6), "kind": kind.name.lower(), "cause": cause,
                        "value": _num(self.value[j]), "limit": _num(self.limit[j])})
        return out


class SafetyRecord:
    """Counters by cause and rings of recent events (preallocated; no allocation per event).

    Stops, faults and clamps go into one ring, late ticks and rejected poses
    into another, so that a flood of the frequent kinds (a loaded machine, a
    tracker reporting ``lost``) cannot push the stops out of the record.

    Parameters
    ----------
    capacity : int
        Recent events kept per ring (the oldest is overwritten; counters are never lost).
    """

    def __init__(self, capacity: int = 128):
        self.stops = _Ring(capacity)  # stop, immediate stop, fault, clamp, joint approach
        self.minor = _Ring(capacity)  # late tick, reject
        # counters[kind, cause]: causes are Check bits for stops/faults, Reject codes for rejects
        self.counts = np.zeros((len(EventKind), 32), np.int64)
        self.max_late_s = 0.0  # the longest late tick's dt

    @property
    def n_events(self) -> int:
        return self.stops.n + self.minor.n

    def add(self, t_ns: int, kind: EventKind, cause: int, value: float, limit: float) -> None:
        """Record one event. ``cause``: a single ``Check`` flag, or a ``Reject`` code."""
        if kind <= EventKind.FAULT:
            self.counts[int(kind), _CHECK_BIT[cause]] += 1
            self.stops.add(t_ns, kind, cause, value, limit)
        elif kind == EventKind.CLAMP or kind == EventKind.JOINT_APPROACH:
            self.counts[int(kind), 0] += 1
            self.stops.add(t_ns, kind, cause, value, limit)
        else:
            self.counts[int(kind), int(cause)] += 1
            self.minor.add(t_ns, kind, cause, value, limit)
            if kind == EventKind.LATE_TICK and value > self.max_late_s:
                self.max_late_s = value

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
        if kind in (EventKind.LATE_TICK, EventKind.CLAMP, EventKind.JOINT_APPROACH):
            return {kind.name.lower(): int(row.sum())} if row.sum() else {}
        return {c.name: int(row[i]) for i, c in enumerate(_CHECKS) if row[i]}

    def recent(self) -> list[dict]:
        """The events still in both rings, oldest first, as plain data."""
        return sorted(self.stops.since(0) + self.minor.since(0), key=lambda e: e["t_s"])

    def stops_since(self, k: int) -> list[dict]:
        """Stops, faults and clamps number ``k`` onwards (0 = the first ever) still in the ring.

        Each: ``t_s`` (the loop's clock, s), ``kind``, ``cause``, ``value``, ``limit``.
        """
        return self.stops.since(k)

    def to_dict(self) -> dict:
        """Counters by kind and cause, plus the recent events (``--stats-json``)."""
        return {
            "stops": self.by_cause(EventKind.STOP),
            "immediate_stops": self.by_cause(EventKind.IMMEDIATE_STOP),
            "faults": self.by_cause(EventKind.FAULT),
            "late_ticks": self.count(EventKind.LATE_TICK),
            "late_tick_max_s": self.max_late_s,
            "target_clamped": self.count(EventKind.CLAMP),
            "joint_approaches": self.count(EventKind.JOINT_APPROACH),
            "rejected": self.by_cause(EventKind.REJECT),
            "events_total": self.n_events,
            "recent_stops": self.stops.since(0),
            "recent_late_ticks_and_rejects": self.minor.since(0),
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
