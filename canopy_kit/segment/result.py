"""What segmentation returns: labels per map point and one record per tree."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from canopy_kit.segment.ground import GroundModel
from canopy_kit.segment.rows import RowAssignment


@dataclass
class TreeRecord:
    """One segmented tree (local metric frame; heights above the ground model)."""

    segment_id: int
    tree_id: str
    row: int
    label: str
    index_in_row: int
    x: float
    y: float
    z: float
    n_points: int
    crown_top_height_m: float
    crown_base_height_m: float
    crown_diameter_m: float
    footprint_area_m2: float


@dataclass
class Segmentation:
    """Labels per point of the input map (``segment_id``, -1 = not a tree) and tree records."""

    labels: np.ndarray
    trees: list[TreeRecord]
    footprints: dict[int, np.ndarray]  # segment_id -> (M, 2) convex hull, counter-clockwise
    rows: RowAssignment
    ground: GroundModel
    height: np.ndarray  # per map point: height above the ground model
    method: str
    params: dict[str, Any]
    crs: str | None = None
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    warnings: list[str] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    classification: np.ndarray | None = None  # per map point: LAS class (segment.classes)
    canopy_band_m: tuple[float, float] = (float("nan"), float("nan"))  # heights segmented
    ceiling_source: str = ""  # "data" or the setting that fixed the band's top
    cut_at_ceiling: list[str] = field(default_factory=list)  # trees whose tops it cut
    ceiling_warning: str = ""  # the warning naming them (a run's check carries it too)
    trunk_feet: dict[str, Any] = field(default_factory=dict)  # trunk-midpoint cut: trunks seen?

    @property
    def n_trees(self) -> int:
        return len(self.trees)

    def table(self) -> pd.DataFrame:
        """One row per tree, in row and label order."""
        columns = list(TreeRecord.__dataclass_fields__)
        return pd.DataFrame([asdict(t) for t in self.trees], columns=columns)

    def carried_warnings(self) -> list[str]:
        """The warnings that a run's check of their own carries (the canopy ceiling's, the
        trunk feet's): the run lists them among its warnings but adds no check for them."""
        feet = self.trunk_feet.get("warning", "") if self.trunk_feet else ""
        return [w for w in (self.ceiling_warning, feet) if w]

    def summary(self) -> dict[str, Any]:
        """Counts, settings, warnings and timings as plain data (for JSON)."""
        return {
            "method": self.method,
            "params": self.params,
            "n_trees": self.n_trees,
            "n_rows": len(self.rows.lines),
            "n_points": int(len(self.labels)),
            "n_tree_points": int((self.labels >= 0).sum()),
            "driving_direction": [float(v) for v in self.rows.direction],
            "driving_direction_source": self.rows.direction_source,
            "crs": self.crs,
            "origin": [float(v) for v in self.origin],
            "warnings": list(self.warnings),
            "canopy_band_m": [round(float(v), 3) for v in self.canopy_band_m],
            "canopy_ceiling_source": self.ceiling_source,
            "cut_at_ceiling": list(self.cut_at_ceiling),
            **({"trunk_feet": self.trunk_feet} if self.trunk_feet else {}),
            "carried_warnings": self.carried_warnings(),
            "timings_s": dict(self.timings),
        }
