"""The paper's almond segmenter (§II.C.2): DBSCAN, then spectral splits of big clusters.

Clusters above ``max_cluster_size`` map points likely hold several overlapping trees; each
is split into ``round(size / max_cluster_size)`` parts by spectral clustering on its
k-nearest-neighbour graph (k = 10): a spectral embedding, then k-means in it.

The paper does not say at what scale the graph's nodes lie. ``graph_cell = 0`` (the
default, the literal reading) makes every voxel point a node, so k = 10 neighbours reach
about 0.16 m in simulated almond foliage; ``graph_cell > 0`` puts the nodes at the
centroids of cells of that size (m) and each point takes its cell's part, so the graph
spans branches rather than leaves (docs/SEGMENTATION.md; the ``almond-scaled`` preset).
"""

from __future__ import annotations

import warnings

import numpy as np

from canopy_kit.core.voxel import voxel_centroids
from canopy_kit.errors import ConfigError
from canopy_kit.plugins.params import NonNegative, Positive, PositiveInt
from canopy_kit.segment.base import Segmenter, check_points, check_weight
from canopy_kit.segment.dbscan import Algorithm, run_dbscan
from canopy_kit.segment.density import first_appearance_order


def check_graph_cell(graph_cell: float) -> None:
    """ConfigError unless ``graph_cell`` is 0 (a node per point) or a positive size in m."""
    if not (isinstance(graph_cell, int | float) and graph_cell >= 0):
        raise ConfigError(f"graph_cell must be >= 0 m (0 = a node per point), got {graph_cell!r}")


def spectral_split(
    xyz: np.ndarray,
    n_parts: int,
    n_neighbors: int = 10,
    eigen_solver: str = "amg",
    random_state: int = 0,
    graph_cell: float = 0.0,
) -> np.ndarray:
    """Split points into ``n_parts`` by spectral clustering on their kNN graph (labels 0..n-1).

    With ``graph_cell > 0`` the graph joins the centroids of cells of that size instead of
    the points, and every point takes its cell's part; k-means then weighs every cell the
    same, however many points it holds. When there are no more cells than parts the split
    falls back to the point graph.

    The symmetrised k-nearest-neighbour connectivity graph of sparse foliage falls apart
    into many small pieces, and each piece would take an eigenvector of its own; so the
    embedding + k-means runs on the graph's largest connected part and every other point
    takes the part of its nearest point there.
    """
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree
    from sklearn.cluster import KMeans
    from sklearn.manifold import spectral_embedding
    from sklearn.neighbors import kneighbors_graph

    check_graph_cell(graph_cell)
    n = len(xyz)
    if n_parts <= 1 or n <= n_parts:
        return np.zeros(n, dtype=np.int64)
    if graph_cell > 0:
        nodes, cell = voxel_centroids(xyz, graph_cell)
        if len(nodes) > n_parts:
            return spectral_split(nodes, n_parts, n_neighbors, eigen_solver, random_state)[cell]
    graph = kneighbors_graph(xyz, min(n_neighbors, n - 1), include_self=False)
    graph = 0.5 * (graph + graph.T)
    _, comp = connected_components(graph, directed=False)
    main = np.flatnonzero(comp == np.bincount(comp).argmax())
    if len(main) <= n_parts:
        main = np.arange(n)
    sub = graph[main][:, main]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # amg/arpack convergence chatter
        emb = spectral_embedding(
            sub,
            n_components=n_parts,
            eigen_solver=eigen_solver,
            random_state=random_state,
            drop_first=False,
        )
    parts = np.zeros(n, dtype=np.int64)
    parts[main] = KMeans(n_parts, n_init=4, random_state=random_state).fit_predict(emb)
    rest = np.setdiff1d(np.arange(n), main)
    if len(rest):
        _, nearest = cKDTree(xyz[main]).query(xyz[rest], workers=-1)
        parts[rest] = parts[main[nearest]]
    return parts


class DBSCANSpectralSegmenter(Segmenter):
    """DBSCAN (``eps``, ``min_samples``) plus spectral splits above ``max_cluster_size``.

    Sizes count map points (``sample_weight``), like ``min_samples``.

    Parameters
    ----------
    eps : float, default 0.8
        DBSCAN neighbourhood radius in metres.
    min_samples : float, default 1300
        Map points within ``eps`` that make a DBSCAN core point.
    max_cluster_size : float, default 45000
        Map points of one tree: a cluster is split into ``round(size / max_cluster_size)``
        parts.
    n_neighbors : int, default 10
        Neighbours per node of the k-nearest-neighbour graph of the spectral split.
    eigen_solver : str, default "amg"
        Solver of the spectral embedding (``amg``, ``arpack`` or ``lobpcg``).
    random_state : int, default 0
        Seed of the embedding and of k-means.
    algorithm : str, default "auto"
        DBSCAN algorithm: ``grid``, ``exact`` or ``auto`` (see ``dbscan``).
    graph_cell : float, default 0.0
        Size (m) of the cells whose centroids are the graph's nodes; 0 = every point a
        node (the paper's literal reading).
    """

    def __init__(
        self,
        eps: Positive = 0.8,
        min_samples: Positive = 1300,
        max_cluster_size: Positive = 45000,
        n_neighbors: PositiveInt = 10,
        eigen_solver: str = "amg",
        random_state: int = 0,
        algorithm: Algorithm = "auto",
        graph_cell: NonNegative = 0.0,
    ) -> None:
        self.eps = eps
        self.min_samples = min_samples
        self.max_cluster_size = max_cluster_size
        self.n_neighbors = n_neighbors
        self.eigen_solver = eigen_solver
        self.random_state = random_state
        self.algorithm = algorithm
        self.graph_cell = graph_cell

    def fit(
        self,
        X: np.ndarray,
        y: None = None,
        sample_weight: np.ndarray | None = None,
    ) -> DBSCANSpectralSegmenter:
        """Cluster ``X`` (N, 3); sets ``labels_``, ``n_clusters_`` and ``splits_``."""
        self.validate_params()
        xyz = check_points(X)
        w = check_weight(sample_weight, len(xyz))
        labels, _ = run_dbscan(xyz, self.eps, self.min_samples, w, self.algorithm)
        out = labels.copy()
        next_label = int(labels.max()) + 1 if len(labels) else 0
        self.splits_: dict[int, int] = {}
        for cluster in range(next_label):
            members = np.flatnonzero(labels == cluster)
            size = w[members].sum()
            n_parts = int(round(size / self.max_cluster_size))
            if n_parts < 2:
                continue
            parts = spectral_split(
                xyz[members],
                n_parts,
                self.n_neighbors,
                self.eigen_solver,
                self.random_state,
                self.graph_cell,
            )
            self.splits_[cluster] = n_parts
            out[members[parts > 0]] = next_label + parts[parts > 0] - 1
            next_label += n_parts - 1
        self.labels_ = first_appearance_order(out)
        self.n_clusters_ = int(self.labels_.max()) + 1 if len(self.labels_) else 0
        return self
