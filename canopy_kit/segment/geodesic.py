"""Shortest-path split of a canopy part between known trees (``adaptive``, step 5).

After the "comparative shortest path" of Tao et al. (2015, ISPRS J. Photogramm. Remote
Sens. 110, 66-76): a tree's foliage is fed from its trunk along its branches, so a point
belongs to the trunk it is joined to by the shortest path through the canopy. The
canopy's points are the nodes of a graph linking each to its ``k`` nearest neighbours;
each tree is a source node at the top of its trunk (its position at the height where its
crown starts), linked to the lowest canopy points above it. One multi-source Dijkstra
(``scipy.sparse.csgraph.dijkstra``, ``min_only``) gives every node its nearest source.

A link may cost more going down than up (``down_penalty``): growth goes up and out from
the trunk, so a path that climbs one crown and comes down into the next is dearer than
its length.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree


def canopy_graph(xyz: np.ndarray, k: int = 8, down_penalty: float = 0.0) -> csr_matrix:
    """Directed (N, N) graph linking each point of ``xyz`` (N, 3) to its ``k`` nearest
    neighbours both ways; a link costs its length times ``1 + down_penalty * drop``, with
    ``drop`` the share of its length that goes down."""
    n = len(xyz)
    k = min(k, n - 1)
    if k < 1:
        return csr_matrix((n, n))
    _, nb = cKDTree(xyz).query(xyz, k=k + 1, workers=-1)
    src = np.repeat(np.arange(n), k)
    dst = nb[:, 1:].ravel()
    # both ways, each link once (a sparse matrix would add up a repeated link's costs)
    pair = np.unique(np.concatenate([src * n + dst, dst * n + src]))
    src, dst = pair // n, pair % n
    return csr_matrix((_link_cost(xyz, src, dst, down_penalty), (src, dst)), shape=(n, n))


def _link_cost(xyz: np.ndarray, src: np.ndarray, dst: np.ndarray, down: float) -> np.ndarray:
    d = xyz[dst] - xyz[src]
    length = np.maximum(np.linalg.norm(d, axis=1), 1e-9)  # a zero would drop the link
    drop = np.maximum(0.0, -d[:, 2]) / length
    return length * (1.0 + down * drop)


def trunk_tops(
    xyz: np.ndarray, positions: np.ndarray, radius: float, quantile: float = 5.0
) -> np.ndarray:
    """Source nodes (K, 3): each tree position (x, y) at the height where its crown starts,
    the ``quantile`` % height of the canopy points within ``radius`` of it (of the
    nearest 50 points in the horizontal plane when none are that close)."""
    tree = cKDTree(xyz[:, :2])
    z = np.empty(len(positions))
    for i, (near, p) in enumerate(zip(tree.query_ball_point(positions, radius), positions)):
        if len(near) < 10:
            near = tree.query(p, k=min(50, len(xyz)))[1]
        z[i] = np.percentile(xyz[np.atleast_1d(near), 2], quantile)
    return np.column_stack([positions, z])


def geodesic_split(
    xyz: np.ndarray,
    positions: np.ndarray,
    k: int = 8,
    down_penalty: float = 0.0,
    seed_radius: float = 0.5,
    seed_links: int = 16,
) -> tuple[np.ndarray, np.ndarray]:
    """Labels (index into ``positions``) of points ``xyz`` (x, y, height) split between
    the trees at ``positions`` (x, y) by the shortest path from each tree's trunk top
    (module docstring), and each point's path length.

    ``k``: neighbours linked per point; ``down_penalty``: extra cost per metre down;
    ``seed_radius``: horizontal radius (m) around a tree position of the points whose low
    height sets its trunk top; ``seed_links``: canopy points each trunk top is linked to
    (its nearest, by their distance). A point no path reaches (a piece the ``k``-nearest
    graph leaves apart) takes the label of the nearest reached point.
    """
    n, n_trees = len(xyz), len(positions)
    if n_trees <= 1 or n == 0:
        return np.zeros(n, dtype=np.int64), np.zeros(n)
    graph = canopy_graph(xyz, k, down_penalty).tocoo()
    tops = trunk_tops(xyz, positions, seed_radius)
    m = min(seed_links, n)
    _, near = cKDTree(xyz).query(tops, k=m)
    near = near.reshape(n_trees, m)
    src = np.repeat(n + np.arange(n_trees), m)
    dst = near.ravel()
    cost = _link_cost(np.vstack([xyz, tops]), src, dst, down_penalty)
    full = coo_matrix(
        (
            np.concatenate([graph.data, cost]),
            (np.concatenate([graph.row, src]), np.concatenate([graph.col, dst])),
        ),
        shape=(n + n_trees, n + n_trees),
    ).tocsr()
    dist, _, sources = dijkstra(
        full, directed=True, indices=n + np.arange(n_trees), min_only=True,
        return_predecessors=True,
    )
    dist, sources = dist[:n], sources[:n]
    labels = np.where(sources >= n, sources - n, -1).astype(np.int64)
    lost = labels < 0
    if lost.any() and not lost.all():
        _, j = cKDTree(xyz[~lost]).query(xyz[lost], workers=-1)
        labels[lost] = labels[~lost][j]
        dist[lost] = np.inf
    elif lost.all():
        _, labels = cKDTree(positions).query(xyz[:, :2], workers=-1)
    return labels.astype(np.int64), dist


def _graph_with_tops(
    xyz: np.ndarray,
    positions: np.ndarray,
    k: int,
    down_penalty: float,
    seed_radius: float,
    seed_links: int,
) -> csr_matrix:
    """The canopy graph plus one node per tree (numbered ``N + tree``) at its trunk top."""
    n, n_trees = len(xyz), len(positions)
    graph = canopy_graph(xyz, k, down_penalty).tocoo()
    tops = trunk_tops(xyz, positions, seed_radius)
    m = min(seed_links, n)
    _, near = cKDTree(xyz).query(tops, k=m)
    src = np.repeat(n + np.arange(n_trees), m)
    dst = near.reshape(n_trees, m).ravel()
    cost = _link_cost(np.vstack([xyz, tops]), src, dst, down_penalty)
    return coo_matrix(
        (
            np.concatenate([graph.data, cost]),
            (np.concatenate([graph.row, src]), np.concatenate([graph.col, dst])),
        ),
        shape=(n + n_trees, n + n_trees),
    ).tocsr()


def path_lengths(
    xyz: np.ndarray,
    positions: np.ndarray,
    k: int = 8,
    down_penalty: float = 0.0,
    seed_radius: float = 0.5,
    seed_links: int = 16,
) -> np.ndarray:
    """(K, N) shortest-path length from each tree's trunk top to each point (inf: none)."""
    n, n_trees = len(xyz), len(positions)
    full = _graph_with_tops(xyz, positions, k, down_penalty, seed_radius, seed_links)
    return dijkstra(full, directed=True, indices=n + np.arange(n_trees))[:, :n]


def scaled_split(
    dist: np.ndarray, start: np.ndarray, n_iter: int = 3, quantile: float = 90.0
) -> np.ndarray:
    """Labels by the path length relative to each tree's reach (a multiplicatively
    weighted geodesic Voronoi): the reach of a tree is the ``quantile`` % path length of
    its points, starting from labels ``start``; a big crown keeps the far points a small
    neighbour's trunk is nearer to."""
    labels = start.copy()
    n_trees = dist.shape[0]
    finite = np.isfinite(dist)
    for _ in range(n_iter):
        reach = np.ones(n_trees)
        for t in range(n_trees):
            d = dist[t, (labels == t) & finite[t]]
            if len(d) >= 10:
                reach[t] = max(np.percentile(d, quantile), 1e-6)
        ok = np.isfinite(dist).any(axis=0)
        new = labels.copy()
        new[ok] = np.argmin(dist[:, ok] / reach[:, None], axis=0)
        if np.array_equal(new, labels):
            break
        labels = new
    return labels
