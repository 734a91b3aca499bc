"""A real tree cloud as a specimen: every point made a small splat the sensors can hit.

A terrestrial scan of a tree is already a sample of its surfaces. To drive the simulator's
sensors past it, the cloud (thinned to ``cell``) becomes splats: flattened octahedra, as
the simulator's leaf clusters are, centred on the points, each about twice as wide as the
distance to its neighbours so that neighbouring splats overlap and the surface stops beams
where the scanned surface did. The tree is moved so its trunk base (the median x, y of its
lowest 2 % of points) is at the origin and its lowest point at z = 0. The full cloud, moved
the same way, is the complete-foliage reference (:attr:`Specimen.reference`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from canopy_kit.sim.scene import leaf_octahedra
from canopy_kit.sim.specimen import Specimen

SPLAT_FACTOR = 2.0  # splat diameter / mean distance to the 4 nearest thinned points
SPLAT_RANGE = (0.03, 0.25)  # metres


def centred_cloud(xyz: np.ndarray) -> np.ndarray:
    """The cloud moved so its trunk base is at x = y = 0 and its lowest point at z = 0."""
    xyz = np.asarray(xyz, float)
    z = xyz[:, 2]
    low = z <= np.quantile(z, 0.02)
    base = np.array([*np.median(xyz[low, :2], axis=0), z.min()])
    return xyz - base


def real_tree(
    path: str | Path,
    cell: float = 0.04,
    seed: int = 0,
    name: str | None = None,
    form: str = "real",
) -> Specimen:
    """The tree cloud in ``path`` (any format :func:`canopy_kit.io.clouds.read_cloud` reads)
    as a specimen of the ``real`` family, with its full cloud as the reference."""
    from canopy_kit.io.clouds import read_cloud

    path = Path(path)
    return splatted(read_cloud(path).xyz, cell, seed, name or path.stem, form)


def splatted(
    xyz: np.ndarray, cell: float = 0.04, seed: int = 0, name: str = "real", form: str = "real"
) -> Specimen:
    """A specimen whose surfaces are splats on the cloud ``xyz`` thinned to ``cell``."""
    from scipy.spatial import cKDTree

    from canopy_kit.voxel import voxel_representatives

    full = centred_cloud(xyz)
    thin = full[voxel_representatives(full, cell)[0]]
    dist = cKDTree(thin).query(thin, k=5)[0][:, 1:].mean(axis=1)
    size = np.clip(SPLAT_FACTOR * dist, *SPLAT_RANGE)
    leaves = leaf_octahedra(thin, size, np.random.default_rng(seed))
    return Specimen(
        name, "real", form, leaves, reference=full, info={"points": len(full), "splats": len(thin)}
    )
