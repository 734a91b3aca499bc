"""DBSCAN with per-point weights and memory that grows linearly with the number of points.

scikit-learn's and Open3D's DBSCAN hold every point's whole neighbourhood at once (about
5 GB and 2.5 GB for a million points at orchard densities). Here neighbourhoods are found
tile by tile (square tiles with an ``eps`` margin): a first pass sums the neighbours'
weights (the core test), a second links core points. Core points in one grid cell of edge
``eps / sqrt(3)`` are always within ``eps`` of each other, so only links between cells are
kept and connected components are found on the (small) cell graph. The clusters equal
DBSCAN's, except that a border point joins the cluster of its nearest core point
(scikit-learn: the first one in its scan order).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from canopy_kit.core.cloud import column_max, column_min
from canopy_kit.errors import InputError

Progress = Callable[[str, float, float], None]


def spatial_tiles(
    xy: np.ndarray, margin: float, target_points: int = 40000
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Square xy tiles of about ``target_points`` each: (owned points, owned + margin).

    Every point is owned by exactly one tile; the second array adds the points of other
    tiles within ``margin`` of the tile, so a neighbourhood of radius ``margin`` around an
    owned point lies entirely inside it.
    """
    xy = np.asarray(xy, dtype=np.float64)[:, :2]
    n = len(xy)
    if n == 0:
        return
    lo, hi = column_min(xy), column_max(xy)
    area = float(np.prod(np.maximum(hi - lo, margin)))
    size = max(np.sqrt(area * target_points / n), 4.0 * margin)
    keys = np.floor((xy - lo) / size).astype(np.int64)
    span = column_max(keys) + 1
    tile_of = keys[:, 0] * span[1] + keys[:, 1]
    order = np.argsort(tile_of, kind="stable")
    bounds = np.searchsorted(tile_of[order], np.arange(span[0] * span[1] + 1))
    for tx in range(span[0]):
        for ty in range(span[1]):
            t = tx * span[1] + ty
            own = order[bounds[t] : bounds[t + 1]]
            if len(own) == 0:
                continue
            near = np.concatenate(
                [
                    order[bounds[a * span[1] + b] : bounds[a * span[1] + b + 1]]
                    for a in range(max(tx - 1, 0), min(tx + 2, span[0]))
                    for b in range(max(ty - 1, 0), min(ty + 2, span[1]))
                ]
            )
            box_lo = lo + np.array([tx, ty]) * size - margin
            box_hi = box_lo + size + 2 * margin
            inside = np.all((xy[near] >= box_lo) & (xy[near] <= box_hi), axis=1)
            yield own, near[inside]


def _pairs(xyz: np.ndarray, members: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """All pairs (i, j) of ``members`` closer than ``eps``, as indices into ``xyz``."""
    if len(members) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pairs = cKDTree(xyz[members]).query_pairs(eps, output_type="ndarray")
    return members[pairs[:, 0]], members[pairs[:, 1]]


def neighbour_weight(
    xyz: np.ndarray, eps: float, sample_weight: np.ndarray | None = None, target_points: int = 40000
) -> np.ndarray:
    """Sum of the weights of the points within ``eps`` of every point (itself included)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if sample_weight is None:
        return (
            cKDTree(xyz)
            .query_ball_point(xyz, eps, return_length=True, workers=-1)
            .astype(np.float64)
        )
    w = np.asarray(sample_weight, dtype=np.float64)
    out = w.copy()
    local = np.full(len(xyz), -1, dtype=np.int64)
    for own, ext in spatial_tiles(xyz, eps, target_points):
        local[own] = np.arange(len(own))
        i, j = _pairs(xyz, ext, eps)
        for a, b in ((i, j), (j, i)):
            la = local[a]
            mine = la >= 0
            out[own] += np.bincount(la[mine], weights=w[b[mine]], minlength=len(own))
        local[own] = -1
    return out


def weighted_dbscan(
    xyz: np.ndarray,
    eps: float,
    min_samples: float,
    sample_weight: np.ndarray | None = None,
    target_points: int = 40000,
    progress: Progress | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """DBSCAN labels (-1 noise) and the core-point mask, in memory linear in the points.

    ``min_samples`` is compared with the summed ``sample_weight`` of the neighbours within
    ``eps`` (the point itself included), as in scikit-learn.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if not eps > 0:
        raise InputError(f"DBSCAN eps must be positive, got {eps}")
    if sample_weight is not None and len(sample_weight) != len(xyz):
        raise InputError(f"sample_weight has {len(sample_weight)} values for {len(xyz)} points")
    n = len(xyz)
    labels = np.full(n, -1, dtype=np.int64)
    if n == 0:
        return labels, np.zeros(0, bool)
    core = neighbour_weight(xyz, eps, sample_weight, target_points) >= min_samples
    if progress:
        progress("DBSCAN", 1, 2)
    core_idx = np.flatnonzero(core)
    if len(core_idx) == 0:
        return labels, core
    cp = xyz[core_idx]
    cell = eps / np.sqrt(3.0) * (1 - 1e-9)
    keys = np.floor((cp - column_min(cp)) / cell).astype(np.int64)
    span = column_max(keys) + 1
    _, cell_of = np.unique(
        (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2], return_inverse=True
    )
    cell_of = cell_of.ravel()
    n_cells = int(cell_of.max()) + 1
    links = []
    for _, ext in spatial_tiles(cp, eps, target_points):
        i, j = _pairs(cp, ext, eps)
        a, b = cell_of[i], cell_of[j]
        keep = a != b
        if keep.any():
            links.append(
                np.unique(np.minimum(a[keep], b[keep]) * n_cells + np.maximum(a[keep], b[keep]))
            )
    ab = np.unique(np.concatenate(links)) if links else np.zeros(0, np.int64)
    graph = sparse.coo_matrix(
        (np.ones(len(ab), np.int8), (ab // n_cells, ab % n_cells)), shape=(n_cells, n_cells)
    )
    _, comp = connected_components(graph, directed=False)
    labels[core_idx] = comp[cell_of]
    border = np.flatnonzero(~core)
    if len(border):
        dist, nearest = cKDTree(cp).query(xyz[border], distance_upper_bound=eps, workers=-1)
        ok = np.isfinite(dist)
        labels[border[ok]] = labels[core_idx[nearest[ok]]]
    if progress:
        progress("DBSCAN", 2, 2)
    return first_appearance_order(labels), core


def first_appearance_order(labels: np.ndarray) -> np.ndarray:
    """Renumber non-negative labels 0..k-1 in order of first appearance (-1 stays)."""
    labels = np.asarray(labels, dtype=np.int64)
    valid = labels >= 0
    if not valid.any():
        return labels.copy()
    uniq, first = np.unique(labels[valid], return_index=True)
    remap = np.full(int(uniq.max()) + 1, -1, dtype=np.int64)
    remap[uniq[np.argsort(first)]] = np.arange(len(uniq))
    return np.where(valid, remap[np.where(valid, labels, 0)], -1)


def _ball_kernel(radius_cells: float) -> np.ndarray:
    """Lattice ball whose cell count is closest to the continuous ball's volume."""
    r = int(np.ceil(radius_cells)) + 1
    g = np.arange(-r, r + 1)
    d2 = (g[:, None, None] ** 2 + g[None, :, None] ** 2 + g[None, None, :] ** 2).astype(float)
    target = 4.0 / 3.0 * np.pi * radius_cells**3
    levels = np.unique(d2[d2 <= (radius_cells + 1) ** 2])
    counts = np.array([(d2 <= v).sum() for v in levels])
    best = levels[int(np.argmin(np.abs(counts - target)))]
    return (d2 <= best).astype(np.float64)


def grid_dbscan(
    xyz: np.ndarray,
    eps: float,
    min_samples: float,
    sample_weight: np.ndarray | None = None,
    cell: float | None = None,
    tile_size: float | None = None,
    progress: Progress | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """DBSCAN on a lattice of edge ``cell`` (default ``eps / 8``), tile by tile.

    Points are binned into cells; a cell is core when the summed weight of the cells whose
    centres lie within ``eps`` reaches ``min_samples`` (an FFT convolution with a ball);
    core cells closer than ``eps`` are linked (a Euclidean distance transform: balls of
    radius ``eps / 2`` around core cells touch) and every other cell within ``eps`` of a
    core cell takes the label of the nearest one. Tiles of ``tile_size`` metres (default
    about 12 eps) carry an ``eps`` margin, and labels are joined across tiles through the
    core cells they share, so memory grows with the tile, not with the map.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    n = len(xyz)
    if not eps > 0:
        raise InputError(f"DBSCAN eps must be positive, got {eps}")
    w = np.ones(n) if sample_weight is None else np.asarray(sample_weight, dtype=np.float64)
    if len(w) != n:
        raise InputError(f"sample_weight has {len(w)} values for {n} points")
    labels = np.full(n, -1, dtype=np.int64)
    if n == 0:
        return labels, np.zeros(0, bool)
    h = eps / 8.0 if cell is None else float(cell)
    lattice = _CellLattice.of(xyz, w, h)
    m = int(np.ceil(eps / h))
    tile = max(int(round((tile_size or 12.0 * eps) / h)), 4 * m)
    span = lattice.span
    tiles = [(tx, ty) for tx in range(0, int(span[0]), tile) for ty in range(0, int(span[1]), tile)]
    core, owned_in = _core_cells(lattice, tiles, tile, m, eps, min_samples, progress)
    cell_label = _label_cells(lattice, core, tiles, owned_in, tile, m, eps, progress)
    if cell_label is None:
        return labels, core[lattice.point_cell]
    labels = cell_label[lattice.point_cell]
    return first_appearance_order(labels), core[lattice.point_cell]


@dataclass
class _CellLattice:
    """The occupied cells of a lattice of edge ``h``: each point's cell and each cell's
    summed weight and integer coordinates (x, y, z from the cloud's minimum corner)."""

    edge: float  # cell edge h, m
    point_cell: np.ndarray  # (N,) index of each point's cell
    weight: np.ndarray  # (C,) summed weight of the points in each cell
    ijk: np.ndarray  # (C, 3) cell coordinates
    span: np.ndarray  # (3,) cells along x, y, z

    @classmethod
    def of(cls, xyz: np.ndarray, w: np.ndarray, h: float) -> _CellLattice:
        lo = column_min(xyz)
        keys = np.floor((xyz - lo) / h).astype(np.int64)
        span = column_max(keys) + 1
        lin = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
        cells, point_cell = np.unique(lin, return_inverse=True)
        point_cell = point_cell.ravel()
        ijk = np.column_stack(
            [cells // (span[1] * span[2]), (cells // span[2]) % span[1], cells % span[2]]
        )
        return cls(h, point_cell, np.bincount(point_cell, weights=w), ijk, span)

    def in_tile(self, tx: int, ty: int, tile: int, m: int) -> tuple[np.ndarray, np.ndarray]:
        """Cells of the tile at (``tx``, ``ty``) with a margin of ``m`` cells, and those it owns
        (without the margin)."""
        ck = self.ijk
        sel = np.flatnonzero(
            (ck[:, 0] >= tx - m)
            & (ck[:, 0] < tx + tile + m)
            & (ck[:, 1] >= ty - m)
            & (ck[:, 1] < ty + tile + m)
        )
        own = sel[
            (ck[sel, 0] >= tx)
            & (ck[sel, 0] < tx + tile)
            & (ck[sel, 1] >= ty)
            & (ck[sel, 1] < ty + tile)
        ]
        return sel, own


def _core_cells(
    lattice: _CellLattice,
    tiles: list[tuple[int, int]],
    tile: int,
    m: int,
    eps: float,
    min_samples: float,
    progress: Progress | None,
) -> tuple[np.ndarray, list[int]]:
    """Pass 1: which cells are core (the owned cells of each tile, with an ``eps`` margin for
    the sums), and how many cells each tile owns."""
    from scipy.signal import fftconvolve

    h = lattice.edge
    kernel = _ball_kernel(eps / h)
    volume_ratio = 4.0 / 3.0 * np.pi * (eps / h) ** 3 / kernel.sum()  # lattice ball -> ball
    core = np.zeros(len(lattice.weight), bool)
    owned_in = []
    for k, (tx, ty) in enumerate(tiles):
        sel, own = lattice.in_tile(tx, ty, tile, m)
        owned_in.append(len(own))
        if len(own) == 0:
            continue
        base = np.array([tx - m, ty - m, 0])
        grid = np.zeros((tile + 2 * m, tile + 2 * m, int(lattice.span[2])))
        loc = lattice.ijk[sel] - base
        grid[loc[:, 0], loc[:, 1], loc[:, 2]] = lattice.weight[sel]
        dens = fftconvolve(grid, kernel, mode="same") * volume_ratio
        lo_own = lattice.ijk[own] - base
        core[own] = dens[lo_own[:, 0], lo_own[:, 1], lo_own[:, 2]] >= min_samples - 1e-6
        if progress:
            progress("DBSCAN", k + 1, 2 * len(tiles))
    return core, owned_in


def _label_cells(
    lattice: _CellLattice,
    core: np.ndarray,
    tiles: list[tuple[int, int]],
    owned_in: list[int],
    tile: int,
    m: int,
    eps: float,
    progress: Progress | None,
) -> np.ndarray | None:
    """Pass 2: link core cells and label the cells near them, tile by tile, then join the
    labels of clusters that share a core cell across tiles. Returns each cell's cluster
    (-1: noise), or None when no cell is core."""
    from scipy import ndimage

    h = lattice.edge
    cell_label = np.full(len(lattice.weight), -1, dtype=np.int64)
    core_pairs: list[np.ndarray] = []  # (global component, core cell) seen in each tile
    next_comp = 0
    for k, (tx, ty) in enumerate(tiles):
        if owned_in[k] == 0:
            continue
        sel, own = lattice.in_tile(tx, ty, tile, m)
        csel = sel[core[sel]]
        if len(csel) == 0:
            continue
        base = np.array([tx - m, ty - m, 0])
        is_core = np.ones((tile + 2 * m, tile + 2 * m, int(lattice.span[2])), bool)
        loc = lattice.ijk[csel] - base
        is_core[loc[:, 0], loc[:, 1], loc[:, 2]] = False
        dist, (ii, jj, kk) = ndimage.distance_transform_edt(is_core, return_indices=True)
        blobs, _ = ndimage.label(dist <= 0.5 * eps / h + 1e-9)
        comp_of_core = blobs[loc[:, 0], loc[:, 1], loc[:, 2]] + next_comp
        next_comp += int(blobs.max()) + 1
        core_pairs.append(np.column_stack([comp_of_core, csel]))
        lo_own = lattice.ijk[own] - base
        near = dist[lo_own[:, 0], lo_own[:, 1], lo_own[:, 2]] <= eps / h + 1e-9
        src = (
            ii[lo_own[near, 0], lo_own[near, 1], lo_own[near, 2]],
            jj[lo_own[near, 0], lo_own[near, 1], lo_own[near, 2]],
            kk[lo_own[near, 0], lo_own[near, 1], lo_own[near, 2]],
        )
        cell_label[own[near]] = blobs[src] + next_comp - int(blobs.max()) - 1
        if progress:
            progress("DBSCAN", len(tiles) + k + 1, 2 * len(tiles))
    if not core_pairs:
        return None
    pairs = np.concatenate(core_pairs)
    n_cells = len(cell_label)
    # Components seen through the same core cell in two tiles are one cluster.
    graph = sparse.coo_matrix(
        (np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1] + next_comp)),
        shape=(next_comp + n_cells, next_comp + n_cells),
    )
    _, joined = connected_components(graph, directed=False)
    ok = cell_label >= 0
    cell_label[ok] = joined[cell_label[ok]]
    return cell_label
