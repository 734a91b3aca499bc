"""Per-tree truth of a session: the tables the simulator writes and evaluation reads.

A truth folder (``SESSION/truth``, see :mod:`canopy_kit.io.session_layout`) holds
``trees.csv`` (one row per tree, :data:`TREE_COLUMNS`), ``trajectory.csv`` (the LiDAR's
true poses: time, x, y, z, qx, qy, qz, qw), ``frame.json`` (the local frame and the rig's
frame names), optionally ``base_trajectory.csv`` (the vehicle frame's poses), and files of
the generator that wrote it (the simulator's ``sim_config.toml``...).

This module owns that format; the simulator writes through it and every stage reads
through it, so no library stage imports :mod:`canopy_kit.sim` (issue 28). Geometry that
only the generator can rebuild (exact crown envelopes, the scene's surfaces) comes from
:meth:`SessionTruth.world`, a world model named by the generator's files and loaded late,
the way plugin entry points are.
"""

from __future__ import annotations

import json
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import pandas as pd

from canopy_kit.core.atomic import atomic_write_text
from canopy_kit.core.geo import LocalFrame
from canopy_kit.errors import InputError
from canopy_kit.io.session_layout import TRUTH_DIR

TREE_COLUMNS = [
    "tree_id",
    "row",
    "index_in_row",
    "label",
    "x",
    "y",
    "z_ground",
    "lat",
    "lon",
    "crown_x",
    "crown_y",
    "crown_z",
    "trunk_height_m",
    "crown_base_height_m",
    "crown_height_m",
    "tree_height_m",
    "crown_diameter_m",
    "crown_diameter_mean_m",
    "crown_volume_m3",
    "sphere_volume_m3",
    "doubled",
]
#: Columns trees.csv adds for a continuous wall (a fruiting wall or hedgerow, issue 52), where
#: a tree's true volume is its cut of the row's wall: the union of the row's crowns between
#: the midpoints to its neighbours' trunks (``cut_start_m``/``cut_end_m`` along the row
#: direction in the local frame, -inf/inf at the wall's ends); ``volume_truth`` names the
#: definition ("trunk-midpoint cut"), ``young`` a young tree.
WALL_COLUMNS = ["cut_volume_m3", "cut_start_m", "cut_end_m", "volume_truth", "young"]
TRUTH_FILES = ("trees.csv", "trajectory.csv", "frame.json")


def write_csv(df: pd.DataFrame, path: Path, float_format: str = "%.6f") -> Path:
    """Write a table as CSV atomically with a fixed float format (byte-identical reruns)."""
    text = df.to_csv(index=False, float_format=float_format, lineterminator="\n")
    return atomic_write_text(path, text)


class WorldModel(Protocol):
    """What a generator rebuilds of a truth folder: the orchard (trees with exact crown
    envelopes, the terrain), the scene (surfaces a map is scored against) and each tree's
    complete foliage (the reference of a volume's measurand, docs/VOLUMES.md)."""

    def orchard(self) -> Any: ...

    def scene(self) -> Any: ...

    def complete_foliage(self, density: float = ...) -> dict[int, Any]:
        """Per tree id: points on every leaf and crown-branch surface, seen or not ((N, 3)),
        about ``density`` per m² (the generator's default when not given)."""
        ...


#: World models are plugins (entry-point group ``canopy_kit.worlds``), each registered under
#: the name of the file that marks the truth folders its generator writes (the simulator's:
#: ``sim_config.toml``), called with the session folder and imported only when a stage asks
#: for exact geometry.
WORLD_GROUP = "worlds"


@dataclass
class SessionTruth:
    """What a session's ``truth/`` folder holds."""

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

    def world(self) -> WorldModel:
        """The generator's model of this session (exact crowns, scene surfaces)."""
        return load_world(self.root)

    def orchard(self) -> Any:
        """The exact orchard (crown envelopes included), rebuilt by the session's generator."""
        return self.world().orchard()


def load_truth(session_dir: str | Path) -> SessionTruth:
    """Read a session's truth (``SESSION/truth``, or the truth folder itself)."""
    root = Path(session_dir)
    truth = root / TRUTH_DIR if (root / TRUTH_DIR).is_dir() else root
    for name in TRUTH_FILES:
        if not (truth / name).exists():
            raise InputError(f"{truth}: not a simulated session's truth folder (no {name})")
    info = json.loads((truth / "frame.json").read_text())
    base = truth / "base_trajectory.csv"
    return SessionTruth(
        truth.parent,
        pd.read_csv(truth / "trees.csv"),
        pd.read_csv(truth / "trajectory.csv"),
        LocalFrame.from_dict(info["frame"]),
        info,
        pd.read_csv(base) if base.exists() else None,
    )


def load_world(session_dir: str | Path) -> WorldModel:
    """The world model of a session, from the generator whose files its truth folder holds."""
    from canopy_kit import plugins

    truth = Path(session_dir) / TRUTH_DIR
    markers = plugins.names(WORLD_GROUP)
    for marker in markers:
        if (truth / marker).exists():
            return plugins.create(
                WORLD_GROUP, marker, {"session_dir": Path(session_dir)}, where=str(truth)
            )
    raise InputError(
        f"{truth}: no generator's files ({', '.join(markers) or 'no world plugin installed'}) "
        "to rebuild the exact world from"
    )


def true_pose_interpolator(
    session_dir: str | Path,
) -> Callable[[np.ndarray], tuple[np.ndarray, Any]]:
    """``f(times) -> (positions, rotations)`` from the session's true trajectory."""
    from scipy.spatial.transform import Rotation, Slerp

    traj = load_truth(session_dir).trajectory
    t = traj["time"].to_numpy()
    pos = traj[["x", "y", "z"]].to_numpy()
    slerp = Slerp(t, Rotation.from_quat(traj[["qx", "qy", "qz", "qw"]].to_numpy()))

    def at(times: np.ndarray) -> tuple[np.ndarray, Rotation]:
        tt = np.clip(times, t[0], t[-1])
        p = np.column_stack([np.interp(tt, t, pos[:, k]) for k in range(3)])
        return p, slerp(tt)

    return at


DEFAULT_ORCHARD_KIND = "pistachio"  # ``canopy_kit.sim.config.OrchardSpec.kind``'s default


def orchard_kind(orchard: str) -> str:
    """The kind of orchard a simulator preset makes (``almond-paper``: ``almond``); any other
    name is returned as it is. The paper's figures and our targets are per kind.

    Results tables name orchards by preset; the preset files (``presets/sim/*.toml``, with
    ``extends``) are read as data here, not through the simulator.
    """
    presets = resources.files("canopy_kit") / "presets" / "sim"
    name, seen = orchard, set()
    while (presets / f"{name}.toml").is_file() and name not in seen:
        seen.add(name)
        data = tomllib.loads((presets / f"{name}.toml").read_text())
        if "kind" in data.get("orchard", {}):
            return str(data["orchard"]["kind"])
        if "extends" not in data:
            return DEFAULT_ORCHARD_KIND
        name = str(data["extends"])
    return orchard
