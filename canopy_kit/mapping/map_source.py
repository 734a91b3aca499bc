"""A finished map (FAST-LIO, LIO-SAM, a handheld scanner) in place of the mapping stage.

``canopy-kit run MAP.laz`` skips odometry: :func:`load_finished_map` reads the map file, its
optional trajectory (CSV ``t,x,y[,z]`` / ``x,y`` or TUM ``t x y z qx qy qz qw``) and its
georeference (the file's CRS or ``--crs``), and returns a :class:`FinishedMap` holding the
same fields the mapping stage's result has, so every later stage runs unchanged.
Coordinates stay local to the reader's round origin (``canopy_kit.io.clouds.local_origin``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from canopy_kit.core.cloud import PointCloud
from canopy_kit.errors import CanopyKitError, InputError
from canopy_kit.io.csv_table import is_number_text

MAP_SUFFIXES = (".las", ".laz", ".pcd", ".ply")
TRAJECTORY_COLUMNS = ["time", "x", "y", "z", "qx", "qy", "qz", "qw"]
# A map whose every point lies within this of the lowest point of its cell holds no tree.
ABOVE_GROUND_M = 0.5
GROUND_CELL_M = 2.0
# A trajectory farther than this from the map's footprint is not in the map's frame.
TRAJECTORY_REACH_M = 100.0
# A trajectory CSV without a header: its columns by their count.
HEADLESS_CSV = {2: ["x", "y"], 3: ["time", "x", "y"], 4: ["time", "x", "y", "z"]}


def is_map_file(path: str | Path) -> bool:
    """True for a point-cloud file (LAS/LAZ/PCD/PLY) given where a bag is expected."""
    p = Path(path)
    return p.suffix.lower() in MAP_SUFFIXES and not p.is_dir()


def as_map_file(source: Any) -> MapFile | None:
    """``source`` as a :class:`MapFile` when it is one or names a map file, else None (a bag)."""
    if isinstance(source, MapFile):
        return source
    return MapFile(Path(source)) if is_map_file(source) else None


def input_path(source: Any) -> Path:
    """The file or folder a run reads: a bag's path or a map file's."""
    return source.path if isinstance(source, MapFile) else Path(source)


@dataclass(frozen=True)
class MapFile:
    """A finished map to run on instead of a bag: the cloud file, the drive's trajectory file
    (in the map's coordinates; optional) and the CRS of a map whose file names none."""

    path: Path
    trajectory: Path | None = None
    crs: str | None = None

    def fingerprint(self) -> dict[str, Any]:
        """What the map stage's cache key holds: each file's identity and the CRS given."""
        from canopy_kit.core.cache import fingerprint

        return {
            "map": fingerprint(self.path),
            "trajectory": fingerprint(self.trajectory) if self.trajectory else None,
            "crs": self.crs,
        }


@dataclass(frozen=True)
class CrsFrame:
    """The georeference of a map whose projected CRS has no EPSG code (a WKT): local
    coordinates plus ``origin`` are coordinates in ``crs`` (same use as ``geo.LocalFrame``)."""

    crs: str
    origin: np.ndarray

    def to_wgs84(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Local (N, 2+) coordinates to latitude, longitude and height."""
        from canopy_kit.core.geo import lonlat_of

        xyz = np.atleast_2d(np.asarray(xyz, float))
        lon, lat = lonlat_of(xyz[:, :2], self.crs, self.origin)
        h = xyz[:, 2] + self.origin[2] if xyz.shape[1] > 2 else np.full(len(xyz), self.origin[2])
        return lat, lon, h

    def to_dict(self) -> dict[str, Any]:
        return {"crs": self.crs, "origin": [float(v) for v in self.origin]}


@dataclass
class FinishedMap:
    """A map made elsewhere, in the shape of the mapping stage's result (``map``,
    ``trajectory``, ``frame``, ``diagnostics``, ``warnings``)."""

    map: PointCloud
    trajectory: pd.DataFrame  # time, x, y, z (map frame); empty without a trajectory file
    frame: Any  # geo.LocalFrame, CrsFrame, or None: not georeferenced
    diagnostics: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    source: str = ""  # the map file's name
    made_elsewhere: bool = True

    @property
    def has_trajectory(self) -> bool:
        return len(self.trajectory) >= 2


def load_finished_map(
    source: MapFile, progress: Callable[[str, float, float], None] | None = None
) -> FinishedMap:
    """The map, trajectory and georeference of ``source``; InputError naming the file when
    it is empty, unreadable, holds no point above the ground, or its CRS is unusable."""
    report = progress or (lambda *_: None)
    report("map file", 0, 1)
    path = Path(source.path)
    cloud, dropped = _read_map(path)
    crs = resolve_crs(path, cloud.crs, source.crs)
    check_points_above_ground(path, cloud)
    cloud.crs = crs
    frame = map_frame(crs, cloud.origin) if crs else None
    trajectory = empty_trajectory()
    if source.trajectory is not None:
        trajectory = read_trajectory(source.trajectory, cloud.origin)
        check_trajectory_on_map(source.trajectory, trajectory, cloud)
    warnings = []
    if dropped:
        warnings.append(f"{path}: {dropped} points with non-finite coordinates left out")
    if crs is None:
        hint = "; its coordinates look projected: give --crs EPSG" if cloud.origin.any() else ""
        warnings.append(
            f"{path}: no CRS in the file and no --crs: the map is not georeferenced "
            f"(trees keep the map's local x/y, no latitude/longitude){hint}"
        )
    steps = np.linalg.norm(np.diff(trajectory[["x", "y"]].to_numpy(float), axis=0), axis=1)
    diagnostics = {
        "source": "map file",
        "map_file": path.name,
        "map_points": len(cloud),
        "crs": crs or "",
        "trajectory_file": source.trajectory.name if source.trajectory else "",
        "path_length_m": float(steps.sum()) if len(trajectory) >= 2 else None,
    }
    report("map file", 1, 1)
    return FinishedMap(cloud, trajectory, frame, diagnostics, warnings, path.name)


def _read_map(path: Path) -> tuple[PointCloud, int]:
    """The map file's points with finite coordinates, and how many were not."""
    from canopy_kit.errors import foreign_message
    from canopy_kit.io.clouds import read_cloud

    try:
        cloud = read_cloud(path)
    except CanopyKitError:
        raise
    except Exception as exc:  # laspy, lazrs and numpy raise many types on corrupt files
        reason = f"{type(exc).__name__}: {foreign_message(str(exc))}"
        raise InputError(f"{path}: map file cannot be read ({reason})") from None
    if len(cloud) == 0:
        raise InputError(f"{path}: map file holds no points")
    finite = np.isfinite(cloud.xyz).all(axis=1)
    if not finite.all():
        cloud = cloud.select(finite)
        if len(cloud) == 0:
            raise InputError(f"{path}: map file holds no finite points")
    return cloud, int((~finite).sum())


def resolve_crs(path: Path, file_crs: str | None, given: str | None) -> str | None:
    """The map's CRS as ``EPSG:n`` or WKT: the file's, or ``--crs`` (an EPSG code or any CRS
    pyproj reads). InputError when it cannot be parsed, is geographic (degrees) or not in
    metres, or when ``--crs`` contradicts the file's."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    chosen, where = file_crs, f"{path}: the file's CRS"
    if given is not None:
        text = str(given).strip()
        text = f"EPSG:{text}" if text.isdigit() else text
        try:
            crs = CRS.from_user_input(text)
        except CRSError as exc:
            raise InputError(f"--crs {given!r}: not a CRS pyproj knows ({exc})") from None
        if file_crs is not None and CRS.from_user_input(file_crs) != crs:
            raise InputError(
                f"{path}: the file's CRS ({_name(file_crs)}) differs from --crs {given}; "
                "leave --crs out to use the file's"
            )
        chosen, where = text, f"--crs {given}"
    if chosen is None:
        return None
    try:
        crs = CRS.from_user_input(chosen)
    except CRSError as exc:
        raise InputError(f"{where}: cannot be parsed ({exc})") from None
    if not crs.is_projected:
        raise InputError(
            f"{where} ({crs.name}) is not a projected CRS: coordinates in degrees cannot be "
            "measured in metres; reproject the map to UTM (e.g. pdal translate, or lidR)"
        )
    unit = crs.axis_info[0].unit_name if crs.axis_info else "metre"
    if unit not in ("metre", "meter"):
        raise InputError(
            f"{where} ({crs.name}) has its axes in {unit}, not metres; reproject the map"
        )
    epsg = crs.to_epsg()
    return f"EPSG:{epsg}" if epsg is not None else crs.to_wkt()


def _name(crs: str) -> str:
    from pyproj import CRS

    return CRS.from_user_input(crs).name


def map_frame(crs: str, origin: np.ndarray) -> Any:
    """The georeference the later stages use: a ``geo.LocalFrame`` for an EPSG code (the same
    object a bag with GNSS gets), else a :class:`CrsFrame`."""
    from canopy_kit.core.geo import LocalFrame

    if crs.startswith("EPSG:"):
        return LocalFrame(int(crs[5:]), float(origin[0]), float(origin[1]), float(origin[2]))
    return CrsFrame(crs, np.asarray(origin, float))


def check_points_above_ground(path: Path, cloud: PointCloud) -> None:
    """InputError unless some point stands more than 0.5 m above the lowest point of its
    2 m cell: a map of bare ground (or a flat slice) holds no tree to measure."""
    cells = np.floor(cloud.xyz[:, :2] / GROUND_CELL_M).astype(np.int64)
    z = cloud.xyz[:, 2]
    lowest = pd.Series(z).groupby([cells[:, 0], cells[:, 1]]).transform("min").to_numpy()
    if not np.any(z - lowest > ABOVE_GROUND_M):
        raise InputError(
            f"{path}: no point stands more than {ABOVE_GROUND_M} m above the ground (the "
            f"lowest point of each {GROUND_CELL_M:g} m cell): the map holds no trees"
        )


def empty_trajectory() -> pd.DataFrame:
    """The trajectory of a map that came without one."""
    return pd.DataFrame({c: pd.Series(dtype=float) for c in ("time", "x", "y", "z")})


def read_trajectory(path: str | Path, origin: np.ndarray) -> pd.DataFrame:
    """A trajectory file in the map file's coordinates, moved to the map's local frame (minus
    ``origin``): TUM (``t x y z qx qy qz qw`` per line, ``#`` comments, as FAST-LIO and
    LIO-SAM tools write) or CSV with a header ``t``/``time``, ``x``, ``y`` [, ``z``]."""
    from canopy_kit.io.clouds import check_input_file

    path = check_input_file(path, "trajectory file")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: trajectory file cannot be read ({exc})") from None
    lines = [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.startswith("#")]
    if not lines:
        raise InputError(f"{path}: trajectory file holds no poses")
    table = _tum(path, lines) if _looks_tum(lines[0]) else _csv(path, text)
    if len(table) < 2:
        raise InputError(f"{path}: trajectory needs at least 2 poses, found {len(table)}")
    known = [c for c in table.columns if c != "z" or table[c].notna().any()]  # z: optional
    if not np.isfinite(table[known].to_numpy(float)).all():
        raise InputError(f"{path}: trajectory holds non-finite values")
    table = table.copy()
    for k, c in enumerate("xyz"):
        if c in table:
            table[c] = table[c] - origin[k]
    return table.reset_index(drop=True)


def _looks_tum(line: str) -> bool:
    parts = line.split()
    return len(parts) == 8 and all(is_number_text(p) for p in parts)


def _tum(path: Path, lines: list[str]) -> pd.DataFrame:
    rows = []
    for k, line in enumerate(lines, 1):
        parts = line.split()
        if len(parts) != 8:
            raise InputError(
                f"{path}: TUM trajectory line {k} has {len(parts)} columns, expected 8 "
                "(t x y z qx qy qz qw)"
            )
        try:
            rows.append([float(p) for p in parts])
        except ValueError:
            raise InputError(
                f"{path}: TUM trajectory line {k} is not numbers: {line[:60]!r}"
            ) from None
    return pd.DataFrame(rows, columns=TRAJECTORY_COLUMNS)


def _csv(path: Path, text: str) -> pd.DataFrame:
    import io

    try:
        table = pd.read_csv(io.StringIO(text), comment="#", skipinitialspace=True)
    except (ValueError, pd.errors.ParserError) as exc:
        raise InputError(f"{path}: trajectory CSV cannot be parsed ({exc})") from None
    table.columns = [str(c).strip().lower() for c in table.columns]
    headless = HEADLESS_CSV.get(len(table.columns))
    if headless and all(is_number_text(c) for c in table.columns):  # no header: by column count
        table = pd.read_csv(io.StringIO(text), comment="#", header=None, names=headless)
    table = table.rename(columns={"t": "time", "timestamp": "time", "stamp": "time"})
    if not {"x", "y"} <= set(table.columns):
        raise InputError(
            f"{path}: trajectory needs columns x and y (CSV with a header t,x,y[,z] or x,y; "
            f"or TUM lines 't x y z qx qy qz qw'), found {', '.join(table.columns) or 'none'}"
        )
    keep = [c for c in TRAJECTORY_COLUMNS if c in table.columns]
    table = table[keep]
    numeric = table.apply(pd.to_numeric, errors="coerce")
    bad = numeric.isna() & table.notna()
    if bad.any().any():
        column = str(bad.any()[bad.any()].index[0])
        row = int(np.flatnonzero(bad[column].to_numpy())[0]) + 2  # + header, 1-based
        raise InputError(f"{path}: trajectory column {column!r} line {row} is not a number")
    if numeric.isna().any().any():
        raise InputError(f"{path}: trajectory has empty cells")
    if "z" not in numeric:
        numeric["z"] = np.nan
    return numeric


def check_trajectory_on_map(path: Path, trajectory: pd.DataFrame, cloud: PointCloud) -> None:
    """InputError when the trajectory runs far from the map: it is in other coordinates
    (e.g. local while the map is in UTM) and would place the drive beside the trees."""
    lo, hi = cloud.bounds()
    xy = trajectory[["x", "y"]].to_numpy(float)
    outside = np.maximum(np.maximum(lo[:2] - xy, xy - hi[:2]), 0.0)
    far = float(np.max(np.linalg.norm(outside, axis=1)))
    if far > TRAJECTORY_REACH_M:
        raise InputError(
            f"{path}: the trajectory runs up to {far:.0f} m outside the map's extent: it is "
            "not in the map file's coordinates"
        )


def run_input(path: Path, trajectory: Path | None = None, crs: str | None = None) -> Any:
    """What ``canopy-kit run`` hands the pipeline: a :class:`MapFile` for a map file, else the
    bag's path; InputError when ``--trajectory`` or ``--crs`` come with a bag, or when the bag
    (or pcap capture) does not exist."""
    if is_map_file(path):
        return MapFile(Path(path), trajectory, crs)
    given = [name for name, v in (("--trajectory", trajectory), ("--crs", crs)) if v is not None]
    if given:
        raise InputError(
            f"{' and '.join(given)}: only for a map file (LAS/LAZ/PCD/PLY), not for {path}"
        )
    from canopy_kit.io.bag import require_bag

    require_bag(path)  # before the preset loads its plugins (scikit-learn, SciPy: 1-2 s)
    return path
