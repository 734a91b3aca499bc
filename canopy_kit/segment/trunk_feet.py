"""Whether a wall's trunks were seen: per row, the returns at the foot of the stem band against
the wall's canopy, and the gaps between the trunks found (issue 52).

With ``cut = "trunk-midpoints"`` a tree is its trunk: a trunk the detector misses makes its
tree join its neighbours (each takes part of it) and their volumes too large. A sensor whose
lowest beams reach the trunks' feet only far along the row (a Livox Mid-360 looks from -7°
upwards) samples them at grazing angles, behind the other trunks, the drip line and the
hanging leaves: few returns at the foot of the stem band, where the detector looks for
trunks. The rule compares a row's map points at its foot (``FOOT_BAND_M`` above the ground,
within ``FOOT_REACH_M`` of the row line) with those of its canopy (``CANOPY_BAND_M``, within
``CANOPY_REACH_M``), both counted per metre of the row, so it does not depend on how long
the drive lingered or how dense the map is: below ``MIN_FOOT_SHARE`` the row's trunks are
probably incomplete. Measured on simulated walls (docs/SEGMENTATION.md "Fruiting walls"):
0.6-1.3 % on the Mid-360, where 1-8 of 19-20 trees were found, 2.5-4.2 % on the 32-ring
and VLP-16 drives, where 19-20 of 19-20 were.

The gaps between consecutive trunks are reported beside it, not judged: on a wall whose
trees stand 0.6-1.5 m apart, a gap twice the median is a missing tree as often as a missed
trunk, and where half the trunks are missed the median itself doubles.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from canopy_kit.segment.rows import RowAssignment

FOOT_BAND_M = (0.3, 0.45)  # the stem band's foot: under a wall's hanging leaves (0.45 m)
FOOT_REACH_M = 0.5  # from the row line: the trunks' line, not the alley's grass
CANOPY_BAND_M = (1.0, 2.0)  # the wall's body, seen by every sensor from the alley
CANOPY_REACH_M = 1.0
MIN_FOOT_SHARE = 0.018  # foot points per canopy point below which trunks were probably missed
DOUBLED_RATIO = 1.6  # a trunk gap this many times the row's median: room for another tree


@dataclass(frozen=True)
class RowFeet:
    """One row: its length, points per metre at the foot and in the canopy, and its trunks'
    along-row positions (sorted) with the gaps between them."""

    row: int
    length_m: float
    foot_per_m: float
    canopy_per_m: float
    trunks_along: np.ndarray

    @property
    def foot_share(self) -> float:
        """Foot points per canopy point (NaN without canopy)."""
        return self.foot_per_m / self.canopy_per_m if self.canopy_per_m > 0 else float("nan")

    @property
    def gaps(self) -> np.ndarray:
        return np.diff(self.trunks_along)

    @property
    def median_gap_m(self) -> float:
        return float(np.median(self.gaps)) if len(self.gaps) else float("nan")

    @property
    def doubled(self) -> int:
        """Trunk gaps of ``DOUBLED_RATIO`` times the median or more (a missed trunk or a
        missing tree)."""
        if len(self.gaps) < 2:
            return 0
        return int((self.gaps >= DOUBLED_RATIO * self.median_gap_m).sum())

    @property
    def trunks_missed(self) -> bool:
        """Whether the row's foot is sampled too thinly for its trunks to be complete."""
        return bool(self.foot_share < MIN_FOOT_SHARE)  # NaN (no canopy): not judged

    def statement(self) -> str:
        """The row's evidence in words."""
        gaps = (
            f"; {len(self.trunks_along)} trunks found over {self.length_m:.1f} m, "
            f"{self.doubled} of {len(self.gaps)} gaps {DOUBLED_RATIO:g}x the median "
            f"{self.median_gap_m:.2f} m or more"
            if len(self.gaps)
            else f"; {len(self.trunks_along)} trunk(s) found over {self.length_m:.1f} m"
        )
        return (
            f"row r{self.row}: {self.foot_per_m:.0f} points per metre at the stem band's foot "
            f"({FOOT_BAND_M[0]:g}-{FOOT_BAND_M[1]:g} m), {100 * self.foot_share:.1f} % of its "
            f"canopy's {self.canopy_per_m:.0f}{gaps}"
        )


@dataclass
class TrunkFeet:
    """The rows' evidence, the trees of the rows whose trunks were probably missed, and the
    warning (empty when no row warns)."""

    rows: list[RowFeet]
    flagged_trees: list[str] = field(default_factory=list)
    warning: str = ""

    def as_dict(self) -> dict[str, Any]:
        """Plain data for metrics.json."""

        def num(v: float, digits: int) -> float | None:
            return round(float(v), digits) if np.isfinite(v) else None

        return {
            "min_foot_share": MIN_FOOT_SHARE,
            "foot_band_m": list(FOOT_BAND_M),
            "canopy_band_m": list(CANOPY_BAND_M),
            "rows": [
                {
                    "row": r.row,
                    "length_m": num(r.length_m, 2),
                    "foot_per_m": num(r.foot_per_m, 1),
                    "canopy_per_m": num(r.canopy_per_m, 1),
                    "foot_share": num(r.foot_share, 4),
                    "trunks": len(r.trunks_along),
                    "median_gap_m": num(r.median_gap_m, 3),
                    "doubled_gaps": r.doubled,
                    "trunks_missed": r.trunks_missed,
                }
                for r in self.rows
            ],
            "flagged_trees": list(self.flagged_trees),
            "warning": self.warning,
        }


def row_feet(
    xyz: np.ndarray, height: np.ndarray, trunks_xy: np.ndarray, rows: RowAssignment
) -> list[RowFeet]:
    """Per fitted row, over its trees' extent: map points ``xyz`` (with their ``height``
    above ground) per metre at the foot and in the canopy, and the trunks ``trunks_xy``
    within ``CANOPY_REACH_M`` of the row line."""
    xy = np.asarray(xyz, dtype=np.float64)[:, :2]
    h = np.asarray(height, dtype=np.float64)
    trunks = np.asarray(trunks_xy, dtype=np.float64).reshape(-1, 2)
    foot_h = (h >= FOOT_BAND_M[0]) & (h < FOOT_BAND_M[1])
    canopy_h = (h >= CANOPY_BAND_M[0]) & (h < CANOPY_BAND_M[1])
    out = []
    for line in rows.lines:
        lo, hi = line.along_range
        length = float(hi - lo)
        along = xy @ line.direction
        near = (along >= lo) & (along <= hi)
        off = np.abs(line.offset(xy))
        n_foot = int((near & foot_h & (off <= FOOT_REACH_M)).sum())
        n_canopy = int((near & canopy_h & (off <= CANOPY_REACH_M)).sum())
        per_m = 1.0 / length if length > 0 else float("nan")
        mine = np.abs(line.offset(trunks)) <= CANOPY_REACH_M if len(trunks) else np.zeros(0, bool)
        out.append(
            RowFeet(
                line.row,
                length,
                n_foot * per_m,
                n_canopy * per_m,
                np.sort(trunks[mine] @ line.direction),
            )
        )
    return out


def trunk_feet(
    xyz: np.ndarray,
    height: np.ndarray,
    trunks_xy: np.ndarray,
    rows: RowAssignment,
    tree_ids: list[str],
    tree_rows: np.ndarray,
) -> TrunkFeet:
    """The evidence of each row (:func:`row_feet`); the trees (``tree_ids``, their
    ``tree_rows``) of the rows whose trunks were probably missed, and the warning naming the
    rows."""
    rows_feet = row_feet(xyz, height, trunks_xy, rows)
    missed = [r for r in rows_feet if r.trunks_missed]
    if not missed:
        return TrunkFeet(rows_feet)
    bad = {r.row for r in missed}
    flagged = [t for t, r in zip(tree_ids, np.asarray(tree_rows)) if int(r) in bad]
    warning = (
        "; ".join(r.statement() for r in missed)
        + f" (below {100 * MIN_FOOT_SHARE:g} %): the trunks' feet are barely sampled, so trunks "
        "were probably missed and their trees joined to their neighbours (volumes too large; "
        f"{len(flagged)} trees flagged in trunk_flags). A sensor that sees the ground beside "
        'the robot, or the adaptive preset, is needed: docs/SEGMENTATION.md "Fruiting walls"'
    )
    return TrunkFeet(rows_feet, flagged, warning)
