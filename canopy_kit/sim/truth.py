"""Per-tree truth of a simulated session: tables written by the simulator, read by evaluation."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from canopy_kit.errors import InputError
from canopy_kit.geo import LocalFrame
from canopy_kit.io.atomic import atomic_write_text
from canopy_kit.sim.orchard import Orchard

TREE_COLUMNS = [
    "tree_id", "row", "index_in_row", "label", "x", "y", "z_ground", "lat", "lon",
    "crown_x", "crown_y", "crown_z", "trunk_height_m", "crown_base_height_m", "crown_height_m",
    "tree_height_m", "crown_diameter_m", "crown_diameter_mean_m", "crown_volume_m3",
    "sphere_volume_m3", "doubled",
]


def tree_table(orchard: Orchard) -> pd.DataFrame:
    """One row per tree with position, sizes, exact crown volume and the sphere-model volume."""
    rows = []
    for t in orchard.trees:
        lat, lon, _ = orchard.frame.to_wgs84(np.array([t.base]))
        z_lo, z_hi = t.crown.z_range
        widest, perpendicular = t.crown.horizontal_extents
        rows.append({
            "tree_id": t.tree_id, "row": t.row, "index_in_row": t.index_in_row, "label": t.label,
            "x": t.base[0], "y": t.base[1], "z_ground": t.base[2], "lat": lat[0], "lon": lon[0],
            "crown_x": t.crown.center[0], "crown_y": t.crown.center[1], "crown_z": t.crown.center[2],
            "trunk_height_m": t.crown_base_height,
            "crown_base_height_m": t.crown_base_height,
            "crown_height_m": z_hi - z_lo,
            "tree_height_m": t.height,
            "crown_diameter_m": widest,
            "crown_diameter_mean_m": 0.5 * (widest + perpendicular),
            "crown_volume_m3": t.crown.volume,
            "sphere_volume_m3": np.pi * widest**3 / 6.0,
            "doubled": bool(t.doubled),
        })
    return pd.DataFrame(rows, columns=TREE_COLUMNS)


def write_csv(df: pd.DataFrame, path: Path, float_format: str = "%.6f") -> Path:
    """Write a table as CSV atomically with a fixed float format (byte-identical reruns)."""
    return atomic_write_text(path, df.to_csv(index=False, float_format=float_format, lineterminator="\n"))


@dataclass
class SessionTruth:
    """What a simulated session's ``truth/`` folder holds."""

    root: Path
    trees: pd.DataFrame
    trajectory: pd.DataFrame  # the LiDAR's poses (``info["sensor_frame"]``)
    frame: LocalFrame
    info: dict
    base_trajectory: pd.DataFrame | None = None  # the vehicle frame's, when the rig has one

    def trajectory_of(self, frame: str) -> pd.DataFrame | None:
        """The true poses of ``frame`` (the LiDAR's or the vehicle's), None for another frame."""
        if frame in ("", self.info.get("sensor_frame")):
            out = self.trajectory
        elif frame == self.info.get("base_frame"):
            out = self.base_trajectory if self.base_trajectory is not None else self.trajectory
        else:
            return None
        out.attrs["frame"] = frame
        return out

    def orchard(self) -> Orchard:
        """Regenerate the exact orchard (crown envelopes included) from the stored config."""
        from canopy_kit.sim.session import regenerate_orchard

        return regenerate_orchard(self.root)


def load_truth(sim_dir: str | Path) -> SessionTruth:
    """Read a simulated session's truth (``SIM_DIR/truth``)."""
    root = Path(sim_dir)
    truth = root / "truth" if (root / "truth").is_dir() else root
    for name in ("trees.csv", "trajectory.csv", "frame.json"):
        if not (truth / name).exists():
            raise InputError(f"{truth}: not a simulated session's truth folder (no {name})")
    info = json.loads((truth / "frame.json").read_text())
    base = truth / "base_trajectory.csv"
    return SessionTruth(truth.parent, pd.read_csv(truth / "trees.csv"),
                        pd.read_csv(truth / "trajectory.csv"), LocalFrame.from_dict(info["frame"]), info,
                        pd.read_csv(base) if base.exists() else None)
