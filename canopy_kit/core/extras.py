"""Optional dependency groups: which extra brings which package, and a clear error when one is missing.

A user who only segments a LAS file needs the core install; mapping a ROS bag, drone
photogrammetry, batch runs and the notebooks each need an extra (see pyproject.toml).
Stages import those packages inside ``with needs_extra(...)`` so that a missing one
raises :class:`~canopy_kit.errors.MissingExtraError` naming the extra to install.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from canopy_kit.errors import MissingExtraError

# Top-level module names each extra provides, and what the extra is for.
EXTRAS: dict[str, tuple[tuple[str, ...], str]] = {
    "mapping": (("kiss_icp", "gtsam", "evo"), "LiDAR(-inertial) odometry and mapping"),
    "aerial": (("pycolmap", "piexif", "tifffile"), "drone photogrammetry (ground truth)"),
    "batch": (("dask", "distributed", "duckdb"), "batch runs and the result store"),
    "notebooks": (("marimo",), "the marimo notebooks"),
    "open3d": (("open3d",), "the simulator, map-to-surface scoring and writing PLY/PCD files"),
}


def extra_of(module: str) -> str | None:
    """The extra that provides top-level module ``module`` (``None`` for core modules)."""
    top = module.split(".")[0]
    return next((name for name, (mods, _) in EXTRAS.items() if top in mods), None)


@contextmanager
def needs_extra(extra: str) -> Iterator[None]:
    """Turn a missing package of ``extra`` into a :class:`MissingExtraError` naming it."""
    if extra not in EXTRAS:
        raise KeyError(f"unknown extra {extra!r}; known: {sorted(EXTRAS)}")
    try:
        yield
    except ModuleNotFoundError as exc:
        missing = exc.name or ""
        if extra_of(missing) != extra:
            raise
        purpose = EXTRAS[extra][1]
        raise MissingExtraError(
            f"{purpose} needs the package {missing.split('.')[0]!r}, which is not installed; "
            f"install the extra with: pip install 'canopy-kit[{extra}]'"
        ) from exc
