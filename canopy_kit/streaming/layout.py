"""The drive's alleys, found online, and which parts of the orchard are finished.

A *pass* is a straight run of the trajectory along the row axis (the axis is the heading of
the first straight run); passes at the same across-row offset share an *alley line*. The
orchard is cut by the alley lines into *regions*: a strip between two neighbouring lines
(one row of trees in a serpentine drive) and the two outer sides. A region is finished:

- a strip: behind the robot while it drives one of the strip's two lines (it has now seen
  both sides of that stretch), and wholly once it drives elsewhere;
- an outer side: once the robot has driven a line other than the one bounding it (the drive
  went the other way, so nothing will come back to its far side);
- everything, at the end of the bag.

Coordinates: ``along`` and ``across`` (to the right) relative to the first pass's start.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np


@dataclass
class AlleyLine:
    """An alley driven at least once: its across-row offset and the passes along it."""

    line_id: int
    offset: float
    n_passes: int = 0


@dataclass
class ActivePass:
    """The pass being driven: its line, direction along the axis (+1/-1) and progress."""

    line_id: int
    sigma: int
    along: float
    start_along: float
    across_sum: float = 0.0
    n: int = 0


@dataclass(frozen=True)
class RegionState:
    """A region's across bounds and how much of it is finished.

    ``sigma * along < frontier`` is finished when ``partial``; all of it when ``complete``.
    """

    key: tuple[int | None, int | None]  # bounding line ids (None: outer side)
    lo: float
    hi: float
    complete: bool
    partial: bool = False
    sigma: int = 1
    frontier: float = -np.inf


@dataclass
class DriveLayout:
    """Passes and alley lines from the sensor positions, fed one sweep at a time."""

    min_pass_m: float = 6.0
    chord_m: float = 2.0
    angle_tol_deg: float = 20.0
    same_line_m: float = 1.5
    origin: np.ndarray | None = None
    axis: np.ndarray | None = None  # unit row direction d (the first pass's heading)
    lines: list[AlleyLine] = field(default_factory=list)
    active: ActivePass | None = None
    last_line: int | None = None
    ended: bool = False
    _recent: deque = field(default_factory=deque)
    _s: float = 0.0
    _run: dict | None = None

    def to_row_frame(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(along, across) of points ``xy`` (N, 2); needs the axis."""
        assert self.axis is not None and self.origin is not None
        rel = np.asarray(xy, float)[..., :2] - self.origin
        right = np.array([self.axis[1], -self.axis[0]])
        return rel @ self.axis, rel @ right

    def update(self, xy: np.ndarray) -> bool:
        """Add a sensor position; True when the passes or lines changed."""
        xy = np.asarray(xy, float)[:2]
        if self._recent:
            self._s += float(np.linalg.norm(xy - self._recent[-1][1]))
        self._recent.append((self._s, xy))
        while len(self._recent) > 2 and self._recent[1][0] <= self._s - self.chord_m:
            self._recent.popleft()
        s0, xy0 = self._recent[0]
        if self._s - s0 < 0.9 * self.chord_m:
            return False  # standing still or barely moving: nothing new about the heading
        heading = (xy - xy0) / np.linalg.norm(xy - xy0)
        return self._advance(xy, heading)

    def _advance(self, xy: np.ndarray, heading: np.ndarray) -> bool:
        cos_tol = np.cos(np.radians(self.angle_tol_deg))
        if self.axis is None:
            run = self._run
            if run is None or float(heading @ run["heading"]) < cos_tol:
                self._run = {"heading": heading, "xy": xy, "s": self._s}
                return False
            if self._s - run["s"] < self.min_pass_m:
                return False
            axis = xy - run["xy"]
            self.axis, self.origin = axis / np.linalg.norm(axis), run["xy"].copy()
            self._run = None
        along, across = self.to_row_frame(xy)
        c = float(heading @ self.axis)
        if abs(c) < cos_tol:  # turning or crossing the rows: no pass
            changed = self.active is not None
            if self.active is not None:
                self.last_line = self.active.line_id
            self.active, self._run = None, None
            return changed
        sigma = 1 if c > 0 else -1
        if self.active is not None and self.active.sigma == sigma:
            a = self.active
            a.along = float(along)
            a.across_sum += float(across)
            a.n += 1
            return False
        if self.active is not None:  # reversed without a turn: end the pass
            self.last_line = self.active.line_id
            self.active = None
        run = self._run
        if run is None or run["sigma"] != sigma:
            self._run = {
                "sigma": sigma,
                "s": self._s,
                "along": float(along),
                "across": [float(across)],
            }
            return True
        run["across"].append(float(across))
        if self._s - run["s"] < self.min_pass_m:
            return False
        offset = float(np.median(run["across"]))
        line = self._line_at(offset)
        line.n_passes += 1
        self.active = ActivePass(
            line.line_id,
            sigma,
            float(along),
            run["along"],
            float(np.sum(run["across"])),
            len(run["across"]),
        )
        self.last_line = line.line_id
        self._run = None
        return True

    def _line_at(self, offset: float) -> AlleyLine:
        for line in self.lines:
            if abs(line.offset - offset) < self.same_line_m:
                return line
        line = AlleyLine(len(self.lines), offset)
        self.lines.append(line)
        self.lines.sort(key=lambda ln: ln.offset)
        return line

    def finish(self) -> None:
        """The bag has ended: everything is finished."""
        if self.active is not None:
            self.last_line = self.active.line_id
        self.active = None
        self.ended = True

    def regions(self, lag: float) -> list[RegionState]:
        """Every region with what of it is finished (``lag`` m behind the robot on a strip)."""
        if self.axis is None or not self.lines:
            return [RegionState((None, None), -np.inf, np.inf, complete=self.ended)]
        bounds = [None, *self.lines, None]
        out = []
        for left, right in zip(bounds[:-1], bounds[1:]):
            lo = left.offset if left is not None else -np.inf
            hi = right.offset if right is not None else np.inf
            key = (left.line_id if left else None, right.line_id if right else None)
            out.append(self._state(key, lo, hi, left, right, lag))
        return out

    def _state(
        self,
        key: tuple[int | None, int | None],
        lo: float,
        hi: float,
        left: AlleyLine | None,
        right: AlleyLine | None,
        lag: float,
    ) -> RegionState:
        if self.ended:
            return RegionState(key, lo, hi, complete=True)
        ids = {ln.line_id for ln in (left, right) if ln is not None}
        active = self.active
        if left is not None and right is not None:  # a strip between two alleys
            if active is not None and active.line_id in ids:
                return RegionState(
                    key,
                    lo,
                    hi,
                    complete=False,
                    partial=True,
                    sigma=active.sigma,
                    frontier=active.sigma * active.along - lag,
                )
            return RegionState(key, lo, hi, complete=True)
        # An outer side: finished once the drive has gone on along another line.
        return RegionState(key, lo, hi, complete=self.last_line not in ids)
