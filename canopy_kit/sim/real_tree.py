"""A real tree cloud as a specimen: every point made a small splat the sensors can hit.

A terrestrial scan of a tree is already a sample of its surfaces. To drive the simulator's
sensors past it, the cloud (thinned to ``cell``) becomes splats: flattened octahedra, as
the simulator's leaf clusters are, centred on the points and lying in the local surface
(thin axis along the normal of the point's 8 neighbours: surface splatting), each 0.6 times
as wide as the distance to its neighbours (at most the cloud's median distance, and 0.12 m).
The surface then stops most beams where the scanned surface did without being thicker or
wider than it: measured on the real trees, the splats' own complete sample has a foliage
envelope within 1-2 % of the cloud's (aRchi's tree 2, the Riegl tree; −4 % on aRchi's 22 m
leafless tree 1), where splats as wide as the spacing added 2-10 % and twice as wide, turned
at random, 10-70 % (docs/VOLUMES.md, "Tree families"). The tree is moved so its trunk base
(the median x, y of its lowest 2 % of points) is at the origin and its lowest point at
z = 0. The full cloud, moved the same way, is the complete-foliage reference
(:attr:`Specimen.reference`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from canopy_kit.sim.scene import leaf_octahedra
from canopy_kit.sim.specimen import Specimen

SPLAT_FACTOR = 0.6  # splat diameter / mean distance to the 4 nearest thinned points
SPLAT_RANGE = (0.02, 0.12)  # metres
NORMAL_NEIGHBOURS = 9  # the point and 8 neighbours: the local surface's plane


def surface_normals(xyz: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """Unit normals: the direction of least spread of each point's neighbours (indices
    ``neighbours``, (N, k)), the local surface's normal."""
    local = xyz[neighbours] - xyz[neighbours].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", local, local)
    return np.linalg.eigh(cov)[1][:, :, 0]


def centred_cloud(xyz: np.ndarray) -> np.ndarray:
    """The cloud moved so its trunk base is at x = y = 0 and its lowest point at z = 0."""
    xyz = np.asarray(xyz, float)
    z = xyz[:, 2]
    low = z <= np.quantile(z, 0.02)
    base = np.array([*np.median(xyz[low, :2], axis=0), z.min()])
    return xyz - base


def real_tree(
    path: str | Path,
    cell: float = 0.03,
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
    xyz: np.ndarray, cell: float = 0.03, seed: int = 0, name: str = "real", form: str = "real"
) -> Specimen:
    """A specimen whose surfaces are splats on the cloud ``xyz`` thinned to ``cell``."""
    from scipy.spatial import cKDTree

    from canopy_kit.core.voxel import voxel_representatives

    full = centred_cloud(xyz)
    thin = full[voxel_representatives(full, cell)[0]]
    dist, near = cKDTree(thin).query(thin, k=NORMAL_NEIGHBOURS)
    spacing = dist[:, 1:5].mean(axis=1)
    # an isolated point at the crown's edge gets no bigger splat than a typical one: a big
    # splat there would stick out of the crown the cloud outlines
    top = min(SPLAT_RANGE[1], SPLAT_FACTOR * float(np.median(spacing)))
    size = np.clip(SPLAT_FACTOR * spacing, SPLAT_RANGE[0], max(top, SPLAT_RANGE[0]))
    leaves = leaf_octahedra(thin, size, np.random.default_rng(seed), surface_normals(thin, near))
    return Specimen(
        name, "real", form, leaves, reference=full, info={"points": len(full), "splats": len(thin)}
    )


def split_plot(
    xyz: np.ndarray,
    band: tuple[float, float] = (1.0, 2.0),
    eps: float = 0.25,
    min_points: int = 30,
) -> list[np.ndarray]:
    """A plot's cloud split into trees: stems found as DBSCAN clusters (x, y) of the points
    ``band`` metres above the plot's lowest point, every point given to the stem nearest it
    in x, y (a Voronoi split: crowns that interleave are cut half-way between stems).
    Returns one cloud per stem, in the plot's coordinates, west to east."""
    from scipy.spatial import cKDTree
    from sklearn.cluster import DBSCAN

    xyz = np.asarray(xyz, float)
    z = xyz[:, 2] - xyz[:, 2].min()
    slab = xyz[(z >= band[0]) & (z <= band[1]), :2]
    labels = DBSCAN(eps=eps, min_samples=min_points).fit_predict(slab)
    stems = np.array([slab[labels == k].mean(axis=0) for k in range(labels.max() + 1)])
    if len(stems) == 0:
        raise ValueError(f"no stem found {band[0]}-{band[1]} m above the plot's lowest point")
    stems = stems[np.argsort(stems[:, 0])]
    owner = cKDTree(stems).query(xyz[:, :2])[1]
    return [xyz[owner == k] for k in range(len(stems))]


def plot_specimens(
    path: str | Path, cell: float = 0.03, seed: int = 0, max_trees: int | None = None
) -> tuple[list[Specimen], np.ndarray]:
    """The trees of a real plot (:func:`split_plot`) as specimens, and where their trunk
    bases stand (K, 2), centred on the plot, x along its longer side."""
    from canopy_kit.io.clouds import read_cloud

    path = Path(path)
    xyz = read_cloud(path).xyz
    if np.ptp(xyz[:, 1]) > np.ptp(xyz[:, 0]):  # the plot's longer side along the row (x)
        xyz = xyz[:, [1, 0, 2]] * [1.0, -1.0, 1.0]
    trees = split_plot(xyz)
    centre = xyz[:, :2].mean(axis=0)
    specimens, bases = [], []
    for k, tree in enumerate(trees[:max_trees]):
        z = tree[:, 2]
        low = z <= np.quantile(z, 0.02)
        bases.append(np.median(tree[low, :2], axis=0) - centre)
        specimens.append(splatted(tree, cell, seed + k, f"{path.stem}-tree{k}", "plot"))
    return specimens, np.asarray(bases)
