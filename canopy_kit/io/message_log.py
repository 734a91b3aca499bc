"""What the reader met on each sensor topic, so that no fault inside a message passes silently.

Per topic (:class:`TopicLog`): messages seen and used, their time span and frame, the
messages dropped (a malformed PointCloud2, a non-finite or impossible IMU sample) with the
reason, and the PointCloud2 messages whose data held bytes their header does not describe.
A topic is unusable (an :class:`~canopy_kit.errors.InputError`, exit 2) when more than
``MAX_DROPPED_SHARE`` of its messages are dropped, when most of its scans carry more points
than their header admits (the header lies: measured, a width halved on every scan gave 5
trees instead of 3), or when its header stamps jump back and stay behind (the sensor clock
jumped: measured, a 15 s jump gave 6 trees instead of 3, the IMU samples of two stretches
of the drive sorted into one).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from canopy_kit.errors import InputError

MAX_DROPPED_SHARE = 0.20  # of a topic's messages; more: the topic is unusable
EARLY_SHARE, EARLY_MIN = 0.5, 50  # stop at once when this share of the first messages is bad
# Bytes beyond what the header describes count as undercounted points from this share of
# the described size on (a few bytes of tail padding are only trimmed).
UNDERCOUNT_SHARE = 0.01
# Stamps that stay behind the topic's latest one for this long (bag log time), or this many
# messages, mean the sensor clock jumped back (a single late or repeated stamp is dropped
# downstream as out of order).
CLOCK_JUMP_S, CLOCK_JUMP_MESSAGES = 1.0, 100
MAX_GYRO_RAD_S = 50.0  # no robot turns at 8 revolutions per second
MAX_ACCEL_M_S2 = 500.0  # 50 g: beyond any MEMS IMU's range on a vehicle


def imu_sample_fault(
    angular_velocity: tuple[float, float, float], linear_acceleration: tuple[float, float, float]
) -> str | None:
    """Why an IMU sample cannot be used (non-finite or impossible values), None when it can."""
    gx, gy, gz = angular_velocity
    ax, ay, az = linear_acceleration
    # The common case in two comparisons (NaN compares false, an overflow to inf fails too).
    if (
        gx * gx + gy * gy + gz * gz <= MAX_GYRO_RAD_S**2
        and ax * ax + ay * ay + az * az <= MAX_ACCEL_M_S2**2
    ):
        return None
    for name, values, limit, unit in (
        ("angular velocity", angular_velocity, MAX_GYRO_RAD_S, "rad/s"),
        ("linear acceleration", linear_acceleration, MAX_ACCEL_M_S2, "m/s²"),
    ):
        if not all(math.isfinite(v) for v in values):
            return f"{name} not finite"
        if math.hypot(*values) > limit:
            return f"{name} above {limit:g} {unit}"
    return None


@dataclass
class TopicLog:
    """One topic's messages as the reader met them (see the module notes)."""

    topic: str
    what: str  # "scans", "IMU samples", "GNSS fixes"
    bag: str = ""  # starts every message
    seen: int = 0
    used: int = 0
    first_stamp: float = math.inf
    last_stamp: float = -math.inf
    frame_id: str = ""
    dropped: dict[int, str] = field(default_factory=dict)  # message index -> reason
    trimmed: dict[int, tuple[int, bool]] = field(
        default_factory=dict
    )  # index -> (bytes, undercounts)
    details: dict[str, str] = field(default_factory=dict)  # reason -> the first such message's text
    index_range: tuple[int, int] = (0, 0)  # [first, last + 1) of the indices seen
    _latest: float = -math.inf  # newest header stamp so far
    _behind: tuple[int, float, int, float] | None = None  # first index, stamp, log ns; run length
    _clock_index: int = -1  # the last message index the clock was watched at

    def _see(self, index: int) -> bool:
        """Count message ``index``; False when it was seen before (the bag read again, e.g. the
        LiDAR-only pass of an extrinsic calibration and then the mapping pass). Within a pass
        indices increase, and a pass reads a contiguous stretch, so the messages seen are
        those of ``index_range``."""
        if not self.seen:
            self.index_range = (index, index + 1)
        elif self.index_range[0] <= index < self.index_range[1]:
            return False
        else:
            self.index_range = (
                min(self.index_range[0], index),
                max(self.index_range[1], index + 1),
            )
        self.seen += 1
        return True

    def use(self, index: int, stamp: float, frame_id: str = "") -> None:
        """Message ``index`` (header ``stamp``) was used."""
        if self._see(index):
            self.used += 1
        if stamp < self.first_stamp:
            self.first_stamp = stamp
        if stamp > self.last_stamp:
            self.last_stamp = stamp
        if frame_id and not self.frame_id:
            self.frame_id = frame_id

    def drop(self, index: int, reason: str, detail: str) -> None:
        """Message ``index`` was dropped for ``reason`` (``detail``: the full text); raises when
        the first messages are mostly unusable."""
        self._see(index)
        self.dropped[index] = reason
        self.details.setdefault(reason, detail)
        self._early_check(len(self.dropped))

    def trim(self, index: int, n_bytes: int, described: int, detail: str) -> None:
        """Used message ``index`` held ``n_bytes`` more than the ``described`` bytes of its points."""
        self.trimmed[index] = (n_bytes, n_bytes > UNDERCOUNT_SHARE * described)
        self.details.setdefault("trimmed", detail)
        self._early_check(self.undercounted)

    def _early_check(self, bad: int) -> None:
        if self.seen >= EARLY_MIN and bad > EARLY_SHARE * self.seen:
            self.check()

    def watch_clock(self, index: int, stamp: float, log_ns: int) -> None:
        """Raise when the header stamps jumped back and stay behind (see ``CLOCK_JUMP_S``)."""
        if index <= self._clock_index:  # the bag read again from an earlier message: a new pass
            self._latest, self._behind = -math.inf, None
        self._clock_index = index
        if stamp > self._latest:
            self._latest, self._behind = stamp, None
            return
        if stamp == self._latest:  # a repeated stamp: not behind
            return
        if self._behind is None:
            self._behind = (index, stamp, log_ns, 0)
        first, at, since, n = self._behind
        self._behind = (first, at, since, n + 1)
        if (log_ns - since) * 1e-9 <= CLOCK_JUMP_S and n + 1 < CLOCK_JUMP_MESSAGES:
            return
        raise InputError(
            f"{self.bag}: topic {self.topic!r}: header stamps jump back {self._latest - at:.3f} s at message "
            f"{first} (t={at:.3f} s after t={self._latest:.3f} s) and stay behind for {n + 1} messages "
            f"over {(log_ns - since) * 1e-9:.1f} s of recording: the sensor clock jumped back, and the "
            "drive cannot be put in time order; re-stamp the messages or cut the bag at the jump"
        )

    @property
    def undercounted(self) -> int:
        """Messages whose data held points beyond those their header describes."""
        return sum(1 for _, under in self.trimmed.values() if under)

    def check(self) -> None:
        """Raise an :class:`InputError` when the topic is unusable (see the module notes)."""
        if not self.seen:
            return
        if len(self.dropped) > MAX_DROPPED_SHARE * self.seen:
            first = min(self.dropped)
            raise InputError(
                f"{self.bag}: topic {self.topic!r}: {len(self.dropped)} of {self.seen} {self.what} unusable "
                f"(more than {100 * MAX_DROPPED_SHARE:.0f} %: {self._reasons()}); first: "
                f"{self.details[self.dropped[first]]}"
            )
        if self.undercounted > MAX_DROPPED_SHARE * self.seen:
            raise InputError(
                f"{self.bag}: topic {self.topic!r}: {self.undercounted} of {self.seen} {self.what} hold more "
                f"data than their header describes; first: {self.details['trimmed']}: the header "
                "(width, height, point_step or row_step) cannot be trusted"
            )

    def _reasons(self) -> str:
        counts: dict[str, int] = {}
        for reason in self.dropped.values():
            counts[reason] = counts.get(reason, 0) + 1
        return ", ".join(
            f"{n} {reason}" for reason, n in sorted(counts.items(), key=lambda kv: -kv[1])
        )

    def warnings(self) -> list[str]:
        """One line per kind of fault the reader worked around."""
        out = []
        if self.dropped:
            first = min(self.dropped)
            out.append(
                f"{self.bag}: topic {self.topic!r}: {len(self.dropped)} of {self.seen} {self.what} "
                f"dropped ({self._reasons()}); first: {self.details[self.dropped[first]]}"
            )
        if self.trimmed:
            extra = sum(n for n, _ in self.trimmed.values())
            out.append(
                f"{self.bag}: topic {self.topic!r}: {len(self.trimmed)} of {self.seen} {self.what} "
                f"hold more data than their header describes ({extra} bytes ignored); first: "
                f"{self.details['trimmed']}"
            )
        return out

    def summary(self) -> dict:
        """The topic as used, for the diagnostics (``mapping.json`` → ``inputs``)."""
        span = (self.first_stamp, self.last_stamp) if self.used else (None, None)
        return {
            "topic": self.topic,
            "frame_id": self.frame_id,
            "messages": self.seen,
            "used": self.used,
            "dropped": len(self.dropped),
            "trimmed": len(self.trimmed),
            "first_stamp": span[0],
            "last_stamp": span[1],
            "duration_s": span[1] - span[0] if self.used else 0.0,
        }

    def restricted(self, lo: int, hi: float) -> TopicLog:
        """The log of messages ``lo <= index < hi`` only (one chunk's own scans)."""
        a, b = max(lo, self.index_range[0]), min(hi, self.index_range[1])
        dropped = {i: r for i, r in self.dropped.items() if lo <= i < hi}
        out = TopicLog(
            self.topic,
            self.what,
            self.bag,
            seen=max(0, int(b - a)),
            frame_id=self.frame_id,
            first_stamp=self.first_stamp,
            last_stamp=self.last_stamp,
            dropped=dropped,
            trimmed={i: t for i, t in self.trimmed.items() if lo <= i < hi},
            details=dict(self.details),
            index_range=(int(a), int(max(a, b))),
        )
        out.used = out.seen - len(dropped)
        return out


def merged(parts: list[TopicLog]) -> TopicLog:
    """One topic's log from those of consecutive stretches of it (each message in one)."""
    out = TopicLog(parts[0].topic, parts[0].what, parts[0].bag)
    for p in parts:
        out.seen += p.seen
        out.used += p.used
        out.first_stamp = min(out.first_stamp, p.first_stamp)
        out.last_stamp = max(out.last_stamp, p.last_stamp)
        out.frame_id = out.frame_id or p.frame_id
        out.dropped.update(p.dropped)
        out.trimmed.update(p.trimmed)
        for k, v in p.details.items():
            out.details.setdefault(k, v)
    out.index_range = (min(p.index_range[0] for p in parts), max(p.index_range[1] for p in parts))
    return out


FLAGS = {
    "scans": ("scans_malformed", "scan_bytes_ignored"),
    "IMU samples": ("imu_samples_dropped", ""),
    "GNSS fixes": ("gnss_fixes_dropped", ""),
}


class MessageLog:
    """The :class:`TopicLog` of every sensor topic a pass read, for one bag."""

    def __init__(self, bag: str) -> None:
        self.bag = bag
        self.topics: dict[str, TopicLog] = {}

    def topic(self, name: str, what: str) -> TopicLog:
        """The log of topic ``name`` (created empty on first use)."""
        if name not in self.topics:
            self.topics[name] = TopicLog(name, what, self.bag)
        return self.topics[name]

    def check(self) -> None:
        """Raise for the first unusable topic (see :meth:`TopicLog.check`)."""
        for log in self.topics.values():
            log.check()

    def warnings(self) -> list[str]:
        """Every topic's warnings (see :meth:`TopicLog.warnings`)."""
        return [w for log in self.topics.values() for w in log.warnings()]

    def flags(self) -> list[str]:
        """Quality flags: what the reader dropped or trimmed."""
        out = []
        for log in self.topics.values():
            dropped, trimmed = FLAGS.get(log.what, ("messages_dropped", ""))
            if log.dropped:
                out.append(dropped)
            if log.trimmed and trimmed:
                out.append(trimmed)
        return out

    def summary(self, roles: dict[str, str | None]) -> dict:
        """``{role: topic summary}`` for ``roles`` (role -> topic name or None)."""
        return {
            role: self.topics[name].summary() if name in self.topics else None
            for role, name in roles.items()
            if name
        }
