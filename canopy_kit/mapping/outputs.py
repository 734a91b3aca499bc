"""Writing a mapping result: LAZ map with CRS, trajectory CSV and TUM, diagnostics, config.

Layout of ``out/``: ``map.laz``, ``trajectory.csv`` (time, x, y, z, qx, qy, qz, qw in the
map frame), ``trajectory.tum`` (the same, space separated, for evo and other tools),
``mapping.json`` (frame, diagnostics, warnings, evaluation when given) and
``mapping_config.toml`` (the config actually used). Every file is written atomically.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from canopy_kit.config import write_config
from canopy_kit.core.atomic import atomic_write_json, atomic_write_text
from canopy_kit.io.las import las_ready, write_las

MAP_NAME = "map.laz"
TRAJECTORY_CSV = "trajectory.csv"
TRAJECTORY_TUM = "trajectory.tum"
REPORT_JSON = "mapping.json"
CONFIG_TOML = "mapping_config.toml"
RIG_TOML = "rig.toml"


def tum_text(trajectory: pd.DataFrame) -> str:
    """TUM format: ``timestamp tx ty tz qx qy qz qw`` per line."""
    cols = ["time", "x", "y", "z", "qx", "qy", "qz", "qw"]
    rows = trajectory[cols].to_numpy()
    return "".join(f"{r[0]:.6f} " + " ".join(f"{v:.6f}" for v in r[1:]) + "\n" for r in rows)


def read_tum(path: str | Path) -> pd.DataFrame:
    """Read a TUM trajectory file into the trajectory table layout."""
    a = np.loadtxt(path, ndmin=2)
    return pd.DataFrame(a[:, :8], columns=["time", "x", "y", "z", "qx", "qy", "qz", "qw"])


def write_rig(rig: Any, path: str | Path) -> Path:
    """The rig a run used (frames, mounts, their sources as comments) as a rig file."""
    import tomlkit

    doc = tomlkit.document()
    doc.add(
        tomlkit.comment(
            f"The sensor rig a canopy-kit mapping run used (trajectory frame {rig.base_name!r})."
        )
    )
    for key, source in sorted(rig.sources.items()):
        doc.add(tomlkit.comment(f"{key}: {source}"))
    tables = rig.rig_file_tables()
    doc["rig"] = tables["rig"]
    doc["frames"] = tables["frames"]
    return atomic_write_text(path, tomlkit.dumps(doc))


def write_mapping_outputs(
    result: Any, out_dir: str | Path, evaluation: dict[str, Any] | None = None
) -> dict[str, Path]:
    """Write a :class:`~canopy_kit.mapping.MappingResult` into ``out_dir``; the written paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "map": write_las(out / MAP_NAME, las_ready(result.map)),
        "trajectory_csv": atomic_write_text(
            out / TRAJECTORY_CSV,
            result.trajectory.to_csv(index=False, float_format="%.6f", lineterminator="\n"),
        ),
        "trajectory_tum": atomic_write_text(out / TRAJECTORY_TUM, tum_text(result.trajectory)),
        "config": write_config(result.config, out / CONFIG_TOML),
    }
    if getattr(result, "rig", None) is not None:
        paths["rig"] = write_rig(result.rig, out / RIG_TOML)
    report = {
        "frame": result.frame.to_dict() if result.frame is not None else None,
        "map": {
            "points": len(result.map),
            "crs": result.map.crs,
            "origin": result.map.origin.tolist(),
            "fields": sorted(result.map.fields),
        },
        "warnings": list(result.warnings),
        "diagnostics": result.diagnostics,
    }
    if evaluation is not None:
        report["evaluation"] = evaluation
    paths["report"] = atomic_write_json(out / REPORT_JSON, report)
    return paths
