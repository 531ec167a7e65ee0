"""Wire protocol between the vision PC and the robot-control PC.

This is the only ``vespro`` module the servo side imports, so it depends on
NumPy and the standard library only.

Framing
-------
Every message travels as one *frame*::

    COBS(packet) 0x00

COBS (consistent overhead byte stuffing) removes every zero byte from the
packet, so ``0x00`` only ever appears as the frame delimiter: a receiver that
joins mid-stream, or sees garbage, drops bytes up to the next ``0x00`` and is
back in sync. The encoder emits only the trailing delimiter; a sink that starts
a stream (a new TCP client, an opened serial port) sends one extra ``0x00``
first so a half-received frame on the other side is terminated.

The packet, all little-endian::

    offset  size  field
    0       1     u8   protocol version (PROTOCOL_VERSION)
    1       1     u8   message type (MsgType)
    2       2     u16  body length L, bytes
    4       L     body (per message type, below)
    4+L     4     u32  CRC-32 (zlib.crc32) of bytes [0, 4+L)

POSE body (packet offsets; L = 188, packet 196 B, frame 198 B on the wire)::

    4    4   u32      seq, per publisher, +1 per POSE (wraps at 2**32)
    8    8   i64      t_capture_ns  image capture stamp, sender's monotonic clock
    16   8   i64      t_send_ns     send stamp, same clock
    24   24  3 x f64  p_world_object, m
    48   32  4 x f64  q_world_object (w, x, y, z), unit norm, w >= 0
    80   12  3 x f32  v_world_object, m/s, world frame
    92   12  3 x f32  w_world_object (angular velocity), rad/s, world frame
    104  84  21 x f32 cov, upper triangle row by row (numpy.triu_indices(6))
                      of the 6x6 covariance of [position (m), orientation
                      error rotation vector (rad)]
    188  2   u16      object_id, index into HELLO's object names
    190  1   u8       status (PoseStatus)
    191  1   u8       probability that the pose is the object's: 0 = not
                      stated, b = 1..255 is p = (b - 1) / 254 (steps of 0.004)

A sender that states no probability sends 0 there, and a decoder that does
not read the byte decodes every message the same: the byte needs no other
layout or protocol version, and either side may leave it out.

Position and quaternion are float64; velocities and covariance are float32:
float32's relative rounding (6e-8) is far below the relative uncertainty of a
velocity estimate or of a covariance, its range covers any variance in m^2 or
rad^2 that matters (values under ~1e-38 lose precision, under 1e-45 become 0),
and float64 would add 108 B per frame (55 % more line time). A
:class:`PoseMsg` stores them as float32 already, so what you construct is bit
for bit what the receiver decodes.

HEARTBEAT body (L = 12, frame 22 B): ``u32 seq, i64 t_send_ns``.

HELLO body (variable, L <= MAX_BODY_BYTES): ``u16 protocol version, f64 nominal
rate Hz, u8 n names, n x (u8 length, UTF-8 bytes)``.

Line budget
-----------
115200 baud 8N1 carries 10 bits per byte: 11520 B/s. One object at 26 Hz
costs 26 x 198 = 5148 B/s (45 %), leaving room for a 1 Hz heartbeat
(22 B/s) and HELLO repeats; two objects at 26 Hz would need 89 %, too tight,
so more than one object needs a faster line (230400 baud or TCP). A frame
takes 198 / 11520 = 17.2 ms on the line.

Refusal
-------
A TCP server that serves no more clients answers a new one with a single line
of UTF-8 text instead of the stream, ``REFUSAL_PREFIX`` followed by the reason
and ``\n``, then closes the connection. The line holds no ``0x00``, so a
:class:`Decoder` fed with it returns no message; a receiver that finds
``REFUSAL_PREFIX`` at the start of what it read before the close can show the
line to its user.

Robustness
----------
``encode`` raises ``ValueError`` on invalid content (wrong shape, non-finite,
out of range). :class:`Decoder` never raises: it counts each rejected frame by
reason (see ``REJECT_REASONS``) and counts gaps in the POSE sequence numbers.

Zenoh
-----
On Zenoh (``vespro serve --zenoh KEY``, ``servo run --connect zenoh/KEY``)
each sample published on the key expression carries one frame, as ``encode``
makes it (the publisher's first sample opens with a lone ``0x00``, as any
stream does); a subscriber feeds the payloads to a :class:`Decoder` in arrival
order. HELLO is repeated every second (a subscriber may join at any
time) and a HEARTBEAT goes out when nothing else did for a second.
:func:`zenoh_config_json5` is the Zenoh configuration both sides use.
"""

from __future__ import annotations

import enum
import math
import struct
import zlib
from dataclasses import dataclass, field
from typing import Union

import numpy as np

__all__ = [
    "PROTOCOL_VERSION",
    "MsgType",
    "PoseStatus",
    "HelloMsg",
    "PoseMsg",
    "HeartbeatMsg",
    "Message",
    "encode",
    "Decoder",
    "DecoderStats",
    "cobs_encode",
    "cobs_decode",
    "CobsError",
    "REJECT_REASONS",
    "POSE_FRAME_BYTES",
    "HEARTBEAT_FRAME_BYTES",
    "MAX_BODY_BYTES",
    "MAX_FRAME_BYTES",
    "LINE_BYTES_PER_S_115200",
    "REFUSAL_PREFIX",
    "ZENOH_ENDPOINT",
    "zenoh_config_json5",
]

PROTOCOL_VERSION = 1

_HEADER = struct.Struct("<BBH")
_CRC = struct.Struct("<I")
_POSE_BODY = struct.Struct("<Iqq3d4d3f3f21fHBB")
_HEARTBEAT_BODY = struct.Struct("<Iq")
_HELLO_HEAD = struct.Struct("<HdB")

MAX_BODY_BYTES = 1024
# Worst-case COBS overhead is one byte per 254, plus the delimiter.
MAX_FRAME_BYTES = _HEADER.size + MAX_BODY_BYTES + _CRC.size + (MAX_BODY_BYTES // 254 + 2) + 1

POSE_FRAME_BYTES = _HEADER.size + _POSE_BODY.size + _CRC.size + 1 + 1
HEARTBEAT_FRAME_BYTES = _HEADER.size + _HEARTBEAT_BODY.size + _CRC.size + 1 + 1
LINE_BYTES_PER_S_115200 = 115200 // 10  # 8N1: start + 8 data + stop bits
#: First bytes of the text line a server sends a client it refuses, before closing (see Refusal).
REFUSAL_PREFIX = b"vespro refused: "

_U32 = 2**32
_I64_MIN, _I64_MAX = -(2**63), 2**63 - 1
_TRIU = np.triu_indices(6)
# A quaternion whose norm is this close to 1 is sent as is: renormalising a
# unit quaternion can change its last bit, and encode(decode(frame)) must give
# the same frame back.
_QUAT_UNIT_TOL = 1e-12
# Decoded quaternions further than this from unit norm are rejected ("value"):
# an encoder always sends a unit quaternion (to ~1e-16).
_QUAT_DECODE_TOL = 1e-6


class MsgType(enum.IntEnum):
    HELLO = 1
    POSE = 2
    HEARTBEAT = 3


class PoseStatus(enum.IntEnum):
    """Tracker state for one object, as sent with each pose."""

    INITIALIZING = 0
    TRACKING = 1
    LOST = 2


REJECT_REASONS = ("cobs", "length", "crc", "version", "unknown_type", "nonfinite", "value", "internal")


def _check_int(name: str, v, lo: int, hi: int) -> int:
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
        raise ValueError(f"{name}: expected an integer, got {type(v).__name__}")
    v = int(v)
    if not lo <= v <= hi:
        raise ValueError(f"{name}: {v} outside [{lo}, {hi}]")
    return v


def _probability_byte(p) -> int:
    """A probability's wire byte (0: not stated, NaN)."""
    try:
        p = float(p)
    except (TypeError, ValueError):
        raise ValueError(f"probability: expected a number, got {type(p).__name__}") from None
    if math.isnan(p):
        return 0
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"probability: {p} outside [0, 1]")
    return 1 + int(round(p * 254))


def _probability_from_byte(b: int) -> float:
    return math.nan if b == 0 else (b - 1) / 254


def _frozen_array(name: str, a, shape: tuple[int, ...], dtype) -> np.ndarray:
    arr = np.asarray(a)
    if arr.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {arr.shape}")
    # Cast first, check after: a float64 above 3.4e38 becomes inf in float32.
    with np.errstate(over="ignore", invalid="ignore"):
        arr = np.array(arr, dtype=dtype, copy=True)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains non-finite values")
    arr.setflags(write=False)
    return arr


def _arrays_equal(a: np.ndarray, b: np.ndarray) -> bool:
    """Bitwise equality (so -0.0 != 0.0; NaN cannot occur in a message)."""
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


@dataclass(frozen=True, eq=False)
class HelloMsg:
    """Sent first on every new connection (and periodically on a serial line).

    Attributes
    ----------
    rate_hz : float
        Nominal POSE rate per object, Hz (> 0).
    object_names : tuple of str
        ``object_id`` in POSE indexes this tuple. At most 255 names, each
        1..255 UTF-8 bytes; the whole body must fit ``MAX_BODY_BYTES``.
    version : int
        Protocol version spoken by the sender.
    """

    rate_hz: float
    object_names: tuple[str, ...]
    version: int = PROTOCOL_VERSION

    def __post_init__(self):
        rate = float(self.rate_hz)
        if not math.isfinite(rate) or rate <= 0.0:
            raise ValueError(f"rate_hz: expected a finite positive rate, got {self.rate_hz!r}")
        names = tuple(self.object_names)
        if len(names) > 255:
            raise ValueError(f"object_names: at most 255 names, got {len(names)}")
        for n in names:
            if not isinstance(n, str):
                raise ValueError(f"object_names: expected str, got {type(n).__name__}")
            b = n.encode("utf-8")
            if not 1 <= len(b) <= 255:
                raise ValueError(f"object_names: {n!r} is {len(b)} UTF-8 bytes, allowed 1..255")
        body_len = _HELLO_HEAD.size + sum(1 + len(n.encode("utf-8")) for n in names)
        if body_len > MAX_BODY_BYTES:
            raise ValueError(f"HELLO body is {body_len} bytes, more than MAX_BODY_BYTES={MAX_BODY_BYTES}")
        object.__setattr__(self, "rate_hz", rate)
        object.__setattr__(self, "object_names", names)
        object.__setattr__(self, "version", _check_int("version", self.version, 0, 0xFFFF))

    def __eq__(self, other):
        if not isinstance(other, HelloMsg):
            return NotImplemented
        return (
            self.version == other.version
            and struct.pack("<d", self.rate_hz) == struct.pack("<d", other.rate_hz)
            and self.object_names == other.object_names
        )

    __hash__ = None


@dataclass(frozen=True, eq=False)
class HeartbeatMsg:
    """Liveness message, sent when there is nothing else to say.

    Attributes
    ----------
    seq : int
        u32, +1 per heartbeat (its own counter, apart from POSE's).
    t_send_ns : int
        Send time on the sender's monotonic clock, ns.
    """

    seq: int
    t_send_ns: int

    def __post_init__(self):
        object.__setattr__(self, "seq", _check_int("seq", self.seq, 0, _U32 - 1))
        object.__setattr__(self, "t_send_ns", _check_int("t_send_ns", self.t_send_ns, _I64_MIN, _I64_MAX))

    def __eq__(self, other):
        if not isinstance(other, HeartbeatMsg):
            return NotImplemented
        return self.seq == other.seq and self.t_send_ns == other.t_send_ns

    __hash__ = None


@dataclass(frozen=True, eq=False)
class PoseMsg:
    """One pose estimate of one object, as sent on the wire.

    Construction validates and canonicalises; the arrays are stored read-only
    in their wire precision, so ``decode(encode(m)) == m`` bit for bit.

    Attributes
    ----------
    seq : int
        u32 sequence number, +1 per POSE sent by a publisher.
    t_capture_ns : int
        Capture stamp of the image(s) the estimate comes from, sender's
        monotonic clock, ns (i64).
    t_send_ns : int
        Send stamp, same clock, ns (i64). ``t_send_ns - t_capture_ns`` is the
        vision-side latency.
    object_id : int
        u16, index into ``HelloMsg.object_names``.
    status : PoseStatus
    p_world_object : ndarray, shape (3,), float64
        Object origin in the world frame, m.
    q_world_object : ndarray, shape (4,), float64
        Object orientation in the world frame, ``(w, x, y, z)``. Normalised
        on construction (unless already unit to 1e-12) and flipped to w >= 0.
        A zero quaternion raises ``ValueError``.
    v_world_object : ndarray, shape (3,), float32
        Linear velocity of the object origin, world frame, m/s.
    w_world_object : ndarray, shape (3,), float32
        Angular velocity, world frame, rad/s.
    cov : ndarray, shape (6, 6), float32
        Covariance of ``[position error (m), orientation error (rad)]``; the
        orientation error is the rotation vector ``e`` with
        ``R_world_object = exp([e]x) @ R_est`` (world frame, left). Symmetrised
        on construction as ``(C + C.T) / 2``; only the upper triangle is sent.
    probability : float
        Probability that the pose is the object's, in [0, 1], or NaN (not
        stated). Stored at its wire precision (the nearest of 255 levels).
    """

    seq: int
    t_capture_ns: int
    t_send_ns: int
    object_id: int
    status: PoseStatus
    p_world_object: np.ndarray
    q_world_object: np.ndarray
    v_world_object: np.ndarray = field(default_factory=lambda: np.zeros(3))
    w_world_object: np.ndarray = field(default_factory=lambda: np.zeros(3))
    cov: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))
    probability: float = math.nan

    def __post_init__(self):
        s = object.__setattr__
        s(self, "probability", _probability_from_byte(_probability_byte(self.probability)))
        s(self, "seq", _check_int("seq", self.seq, 0, _U32 - 1))
        s(self, "t_capture_ns", _check_int("t_capture_ns", self.t_capture_ns, _I64_MIN, _I64_MAX))
        s(self, "t_send_ns", _check_int("t_send_ns", self.t_send_ns, _I64_MIN, _I64_MAX))
        s(self, "object_id", _check_int("object_id", self.object_id, 0, 0xFFFF))
        try:
            s(self, "status", PoseStatus(self.status))
        except ValueError:
            raise ValueError(f"status: {self.status!r} is not a PoseStatus") from None
        s(self, "p_world_object", _frozen_array("p_world_object", self.p_world_object, (3,), np.float64))
        q = _frozen_array("q_world_object", self.q_world_object, (4,), np.float64)
        n = float(np.sqrt(q @ q))
        if n == 0.0 or not math.isfinite(n):
            raise ValueError(f"q_world_object: cannot normalise {q}")
        if abs(n - 1.0) > _QUAT_UNIT_TOL or q[0] < 0.0:
            q = q / n if abs(n - 1.0) > _QUAT_UNIT_TOL else q.copy()
            if q[0] < 0.0:
                q = -q
            q.setflags(write=False)
        s(self, "q_world_object", q)
        s(self, "v_world_object", _frozen_array("v_world_object", self.v_world_object, (3,), np.float32))
        s(self, "w_world_object", _frozen_array("w_world_object", self.w_world_object, (3,), np.float32))
        c = np.asarray(self.cov)
        if c.shape != (6, 6):
            raise ValueError(f"cov: expected shape (6, 6), got {c.shape}")
        with np.errstate(over="ignore", invalid="ignore"):
            c = 0.5 * (c.astype(np.float64) + c.astype(np.float64).T)
        s(self, "cov", _frozen_array("cov", c, (6, 6), np.float32))

    def __eq__(self, other):
        if not isinstance(other, PoseMsg):
            return NotImplemented
        return (
            self.seq == other.seq
            and self.t_capture_ns == other.t_capture_ns
            and self.t_send_ns == other.t_send_ns
            and self.object_id == other.object_id
            and self.status == other.status
            and _arrays_equal(self.p_world_object, other.p_world_object)
            and _arrays_equal(self.q_world_object, other.q_world_object)
            and _arrays_equal(self.v_world_object, other.v_world_object)
            and _arrays_equal(self.w_world_object, other.w_world_object)
            and _arrays_equal(self.cov, other.cov)
            and _probability_byte(self.probability) == _probability_byte(other.probability)
        )

    __hash__ = None


Message = Union[HelloMsg, PoseMsg, HeartbeatMsg]


# --- COBS ---------------------------------------------------------------------


class CobsError(ValueError):
    """Malformed COBS data."""


def cobs_encode(data: bytes) -> bytes:
    """COBS-encode ``data``; the result contains no zero byte (no delimiter added)."""
    data = bytes(data)
    if len(data) < 254:
        # No run can reach 254 bytes: each zero becomes the distance to the
        # next zero (or to the end), with one code byte in front. Vectorised
        # because a POSE packet has ~90 zero bytes.
        a = np.frombuffer(data, dtype=np.uint8)
        bounds = np.concatenate(([-1], np.flatnonzero(a == 0), [len(a)]))
        out = np.empty(len(a) + 1, dtype=np.uint8)
        out[1:] = a
        out[bounds[:-1] + 1] = np.diff(bounds)
        return out.tobytes()
    out = bytearray()
    blocks = data.split(b"\x00")
    last = len(blocks) - 1
    for i, block in enumerate(blocks):
        full = len(block) > 0 and len(block) % 254 == 0
        while len(block) >= 254:
            out.append(255)
            out += block[:254]
            block = block[254:]
        # A final run of exactly k*254 bytes needs no closing code byte (the
        # 0xFF code already says "no zero follows").
        if not (i == last and full):
            out.append(len(block) + 1)
            out += block
    return bytes(out)


def cobs_decode(enc: bytes) -> bytes:
    """Inverse of :func:`cobs_encode` (without the delimiter).

    Raises
    ------
    CobsError
        A zero byte inside, or a code byte pointing past the end.
    """
    enc = bytes(enc)
    n = len(enc)
    if 0 in enc:
        raise CobsError("zero byte inside a frame")
    # Walk the code bytes: each one after the first becomes the zero it
    # stands for, or disappears if the code before it was 0xFF (no zero).
    out = bytearray(enc)
    drop = [0]
    i = 0
    prev = 0
    while i < n:
        code = enc[i]
        if i > 0:
            if prev == 255:
                drop.append(i)
            else:
                out[i] = 0
        prev = code
        i += code
    if i > n:
        raise CobsError(f"last code byte runs {i - n} bytes past the end ({n})")
    for k in reversed(drop):
        del out[k]
    return bytes(out)


# --- encode -------------------------------------------------------------------


def _body(msg: Message, t_send_ns: int | None) -> tuple[int, bytes]:
    if isinstance(msg, PoseMsg):
        floats = (msg.p_world_object.tolist() + msg.q_world_object.tolist() + msg.v_world_object.tolist()
                  + msg.w_world_object.tolist() + msg.cov[_TRIU].tolist())
        # Construction already refused non-finite values; checked again here
        # because nothing non-finite may ever leave this module.
        if not all(map(math.isfinite, floats)):
            raise ValueError("POSE contains non-finite values")
        body = _POSE_BODY.pack(
            msg.seq,
            msg.t_capture_ns,
            msg.t_send_ns if t_send_ns is None else t_send_ns,
            *floats,
            msg.object_id,
            int(msg.status),
            _probability_byte(msg.probability),
        )
        return MsgType.POSE, body
    if isinstance(msg, HeartbeatMsg):
        return MsgType.HEARTBEAT, _HEARTBEAT_BODY.pack(msg.seq, msg.t_send_ns if t_send_ns is None else t_send_ns)
    if isinstance(msg, HelloMsg):
        parts = [_HELLO_HEAD.pack(msg.version, msg.rate_hz, len(msg.object_names))]
        for name in msg.object_names:
            b = name.encode("utf-8")
            parts.append(bytes([len(b)]) + b)
        return MsgType.HELLO, b"".join(parts)
    raise ValueError(f"not a wire message: {type(msg).__name__}")


def encode(msg: Message, t_send_ns: int | None = None) -> bytes:
    """One complete frame for ``msg``: ``COBS(packet) + b"\\x00"``.

    Parameters
    ----------
    msg : HelloMsg, PoseMsg or HeartbeatMsg
    t_send_ns : int, optional
        Send stamp to write instead of ``msg.t_send_ns`` (POSE and
        HEARTBEAT), so a publisher can stamp at send time without copying
        the message.

    Raises
    ------
    ValueError
        ``msg`` is not a message type, or ``t_send_ns`` is not an i64.
        (Content was validated when the message was constructed:
        non-finite values, bad shapes and out of range integers raise
        ``ValueError`` there.)
    """
    if t_send_ns is not None:
        t_send_ns = _check_int("t_send_ns", t_send_ns, _I64_MIN, _I64_MAX)
    mtype, body = _body(msg, t_send_ns)
    packet = _HEADER.pack(PROTOCOL_VERSION, int(mtype), len(body)) + body
    packet += _CRC.pack(zlib.crc32(packet))
    return cobs_encode(packet) + b"\x00"


# --- decode -------------------------------------------------------------------


class _Reject(Exception):
    def __init__(self, reason: str):
        self.reason = reason


def _decode_pose(body: bytes) -> PoseMsg:
    if len(body) != _POSE_BODY.size:
        raise _Reject("length")
    v = _POSE_BODY.unpack(body)
    seq, t_cap, t_send = v[0], v[1], v[2]
    object_id, status = v[37], v[38]
    if not all(map(math.isfinite, v[3:37])):
        raise _Reject("nonfinite")
    if status not in PoseStatus._value2member_map_:
        raise _Reject("value")
    qw, qx, qy, qz = v[6:10]
    if abs(math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz) - 1.0) > _QUAT_DECODE_TOL or qw < 0.0:
        raise _Reject("value")
    p = np.array(v[3:6], dtype=np.float64)
    q = np.array(v[6:10], dtype=np.float64)
    lin = np.array(v[10:13], dtype=np.float32)
    ang = np.array(v[13:16], dtype=np.float32)
    tri = np.array(v[16:37], dtype=np.float32)
    cov = np.empty((6, 6), dtype=np.float32)
    cov[_TRIU] = tri
    cov.T[_TRIU] = tri
    # Everything is checked above and the struct types bound the integers, so
    # skip __post_init__ (it would cost most of the decode time).
    msg = object.__new__(PoseMsg)
    s = object.__setattr__
    for name, val in (("seq", seq), ("t_capture_ns", t_cap), ("t_send_ns", t_send),
                      ("object_id", object_id), ("status", PoseStatus(status)),
                      ("probability", _probability_from_byte(v[39]))):
        s(msg, name, val)
    for name, arr in (("p_world_object", p), ("q_world_object", q), ("v_world_object", lin),
                      ("w_world_object", ang), ("cov", cov)):
        arr.setflags(write=False)
        s(msg, name, arr)
    return msg


def _decode_heartbeat(body: bytes) -> HeartbeatMsg:
    if len(body) != _HEARTBEAT_BODY.size:
        raise _Reject("length")
    seq, t_send = _HEARTBEAT_BODY.unpack(body)
    return HeartbeatMsg(seq, t_send)


def _decode_hello(body: bytes) -> HelloMsg:
    if len(body) < _HELLO_HEAD.size:
        raise _Reject("length")
    version, rate, n = _HELLO_HEAD.unpack_from(body)
    if not math.isfinite(rate):
        raise _Reject("nonfinite")
    names = []
    i = _HELLO_HEAD.size
    for _ in range(n):
        if i >= len(body):
            raise _Reject("length")
        k = body[i]
        if k == 0 or i + 1 + k > len(body):
            raise _Reject("length")
        try:
            names.append(body[i + 1 : i + 1 + k].decode("utf-8"))
        except UnicodeDecodeError:
            raise _Reject("value") from None
        i += 1 + k
    if i != len(body):
        raise _Reject("length")
    try:
        return HelloMsg(rate, tuple(names), version)
    except ValueError:
        raise _Reject("value") from None


_DECODERS = {
    MsgType.POSE: _decode_pose,
    MsgType.HEARTBEAT: _decode_heartbeat,
    MsgType.HELLO: _decode_hello,
}


def decode_frame(frame: bytes) -> Message:
    """Decode one frame without its delimiter; raises ``_Reject`` (internal)."""
    try:
        packet = cobs_decode(frame)
    except CobsError:
        raise _Reject("cobs") from None
    if len(packet) < _HEADER.size + _CRC.size:
        raise _Reject("length")
    (crc,) = _CRC.unpack_from(packet, len(packet) - _CRC.size)
    if zlib.crc32(packet[: -_CRC.size]) != crc:
        raise _Reject("crc")
    version, mtype, body_len = _HEADER.unpack_from(packet)
    if version != PROTOCOL_VERSION:
        raise _Reject("version")
    if body_len != len(packet) - _HEADER.size - _CRC.size:
        raise _Reject("length")
    dec = _DECODERS.get(mtype)
    if dec is None:
        raise _Reject("unknown_type")
    return dec(packet[_HEADER.size : -_CRC.size])


@dataclass(frozen=True)
class DecoderStats:
    """Counters of a :class:`Decoder` (cumulative since construction).

    Attributes
    ----------
    bytes_in : int
    frames_ok : int
        Frames decoded into a message.
    rejected : dict
        Rejected frames by reason (keys ``REJECT_REASONS``).
    seq_gaps : int
        POSE sequence numbers skipped (sum of ``new - last - 1`` over forward jumps).
    seq_duplicates : int
        POSE with the same seq as the previous one.
    seq_resets : int
        POSE seq going backwards (or jumping >= 2**31): taken as a new stream.
    """

    bytes_in: int
    frames_ok: int
    rejected: dict
    seq_gaps: int
    seq_duplicates: int
    seq_resets: int

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())


class Decoder:
    """Streaming frame decoder: bytes in, messages out, never raises.

    Feed it whatever arrived, in pieces of any size. Frames are cut at each
    ``0x00``; a frame that fails any check is dropped and counted by reason,
    and decoding resumes with the next frame. An unterminated frame longer
    than ``MAX_FRAME_BYTES`` is dropped (reason ``"length"``) together with
    everything up to the next delimiter.
    """

    def __init__(self):
        self._buf = bytearray()
        self._skipping = False
        self._last_pose_seq: int | None = None
        self.bytes_in = 0
        self.frames_ok = 0
        self.rejected = {r: 0 for r in REJECT_REASONS}
        self.seq_gaps = 0
        self.seq_duplicates = 0
        self.seq_resets = 0

    def reset_stream(self) -> None:
        """Start a new stream (a new connection); counters stay.

        A partial frame left from the old stream is dropped and counted as
        rejected (``"length"``: truncated); sequence tracking starts over.
        """
        if self._buf and not self._skipping:
            self.rejected["length"] += 1
        self._buf.clear()
        self._skipping = False
        self._last_pose_seq = None

    def stats(self) -> DecoderStats:
        return DecoderStats(self.bytes_in, self.frames_ok, dict(self.rejected),
                            self.seq_gaps, self.seq_duplicates, self.seq_resets)

    def feed(self, data) -> list[Message]:
        """Consume ``data`` (bytes-like); return the messages completed by it, in order."""
        out: list[Message] = []
        try:
            data = bytes(data)
        except Exception:
            self.rejected["internal"] += 1
            return out
        self.bytes_in += len(data)
        if not data:
            return out
        buf = self._buf
        start = 0
        while True:
            k = data.find(0, start)
            if k < 0:
                if not self._skipping:
                    buf += data[start:]
                    if len(buf) > MAX_FRAME_BYTES:
                        self.rejected["length"] += 1
                        buf.clear()
                        self._skipping = True
                break
            if self._skipping:
                self._skipping = False
                buf.clear()
            else:
                buf += data[start:k]
                if buf:
                    self._one(bytes(buf), out)
                    buf.clear()
            start = k + 1
        return out

    def _one(self, frame: bytes, out: list) -> None:
        if len(frame) > MAX_FRAME_BYTES:
            self.rejected["length"] += 1
            return
        try:
            msg = decode_frame(frame)
        except _Reject as r:
            self.rejected[r.reason] += 1
            return
        except Exception:
            # Belt and braces: a bug here must not take the receiver down.
            self.rejected["internal"] += 1
            return
        self.frames_ok += 1
        if isinstance(msg, PoseMsg):
            self._track_seq(msg.seq)
        elif isinstance(msg, HelloMsg):
            self._last_pose_seq = None
        out.append(msg)

    def _track_seq(self, seq: int) -> None:
        last = self._last_pose_seq
        self._last_pose_seq = seq
        if last is None:
            return
        d = (seq - last) % _U32
        if d == 1:
            return
        if d == 0:
            self.seq_duplicates += 1
        elif d < _U32 // 2:
            self.seq_gaps += d - 1
        else:
            self.seq_resets += 1


# --- Zenoh peers --------------------------------------------------------------

#: Where the publisher listens and subscribers connect by default: loopback only.
ZENOH_ENDPOINT = "tcp/127.0.0.1:7447"


def zenoh_config_json5(mode: str = "peer", listen=(), connect=()) -> str:
    """A Zenoh peer configuration (JSON5 text for ``zenoh.Config.from_json5``).

    Multicast scouting is off, so a peer finds no other by itself and sends
    nothing beyond the endpoints given: a peer on one machine listens or
    connects on ``tcp/127.0.0.1:PORT``; across machines every peer connects
    to a router (``mode="client"`` or ``"peer"``, ``connect=("tcp/ROUTER:7447",)``).

    Parameters
    ----------
    mode : str
        ``peer``, ``client`` or ``router``.
    listen, connect : sequence of str
        Zenoh endpoints (``tcp/HOST:PORT``); an empty ``listen`` opens no port.
    """
    import json

    if mode not in ("peer", "client", "router"):
        raise ValueError(f"zenoh mode: expected peer, client or router, got {mode!r}")
    return json.dumps({"mode": mode, "listen": {"endpoints": list(listen)}, "connect": {"endpoints": list(connect)},
                       "scouting": {"multicast": {"enabled": False}}})
