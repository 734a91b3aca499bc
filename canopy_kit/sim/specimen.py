"""One tree as the simulator's sensors see it, whatever family built it: its leaves and wood.

A :class:`Specimen` stands with its trunk base at the origin (x, y, z in metres, z up). It
holds the leaf clusters (flattened octahedra, six vertices each, as
:func:`canopy_kit.sim.scene.leaf_octahedra` makes them), the wood inside the crown (branches,
labelled as the tree's) and the trunk below the crown (not canopy), and what its family knows
exactly: the volume of the envelope it was drawn in, when it was drawn in one.

:meth:`Specimen.complete_foliage` samples every leaf and branch surface of the crown densely,
seen or not: the complete-foliage reference against which a drive's estimate is scan-induced
error (docs/VOLUMES.md, "Tree families").

Families (each in its own module): ``envelope`` (the orchard simulator's crowns,
:func:`from_orchard_tree`), ``lobe_union`` (:mod:`canopy_kit.sim.lobe_union`), ``grown``
(space colonisation, :mod:`canopy_kit.sim.grown`) and ``real`` (a real tree cloud made into
splats, :mod:`canopy_kit.sim.real_tree`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from canopy_kit.sim.scene import octahedra_faces

EMPTY_MESH = (np.empty((0, 3)), np.empty((0, 3), dtype=np.int64))
FAMILIES = ("envelope", "lobe_union", "grown", "real")
COMPLETE_DENSITY = 4000.0  # points per m² of leaf and branch surface in the complete foliage


@dataclass(frozen=True)
class Specimen:
    """One tree at the origin: leaf clusters, crown wood, trunk, and its family's exact facts.

    ``leaves``: ``(6 m, 3)`` vertices of ``m`` octahedral leaf clusters; ``wood``: the
    branches inside the crown as a mesh (vertices, faces); ``trunk``: the stem below the crown
    (not canopy, as the pipeline removes it). ``envelope_m3``: the exact volume of the
    envelope the foliage was drawn in (None for families grown without one). ``young``: a
    young tree with few leaves (measured as the enclosing ellipsoid of its foliage).
    ``reference``: the complete foliage when it is known as points rather than sampled from
    the surfaces (a real tree's full cloud).
    """

    name: str
    family: str
    form: str
    leaves: np.ndarray
    wood: tuple[np.ndarray, np.ndarray] = EMPTY_MESH
    trunk: tuple[np.ndarray, np.ndarray] = EMPTY_MESH
    envelope_m3: float | None = None
    young: bool = False
    reference: np.ndarray | None = None
    info: dict = field(default_factory=dict)

    @property
    def n_leaf_clusters(self) -> int:
        """Number of leaf clusters."""
        return len(self.leaves) // 6

    def crown_mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """Leaves and crown wood as one triangle mesh (what carries the tree's id)."""
        m = self.n_leaf_clusters
        wv, wf = self.wood
        verts = np.concatenate([self.leaves, wv])
        faces = np.concatenate([octahedra_faces(m), np.asarray(wf) + len(self.leaves)])
        return verts, faces.astype(np.int64)

    def complete_foliage(self, density: float = COMPLETE_DENSITY, seed: int = 0) -> np.ndarray:
        """Points on every leaf and crown-branch surface, ``density`` per m² (at least every
        vertex): the crown as if every surface were seen, with no noise and no occlusion; a
        real tree's full cloud (``reference``) where there is one."""
        if self.reference is not None:
            return self.reference
        verts, faces = self.crown_mesh()
        return sample_mesh(verts, faces, density, np.random.default_rng(seed))

    def extent(self) -> tuple[np.ndarray, np.ndarray]:
        """Lowest and highest corner of the crown's axis-aligned box."""
        verts = self.crown_mesh()[0]
        return verts.min(axis=0), verts.max(axis=0)

    def turned(self, yaw: float, name: str | None = None) -> Specimen:
        """The same tree turned by ``yaw`` radians about its trunk (the z axis)."""
        c, s = np.cos(yaw), np.sin(yaw)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

        def turn(mesh: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
            return np.asarray(mesh[0]) @ rot.T, mesh[1]

        return Specimen(
            name or self.name,
            self.family,
            self.form,
            self.leaves @ rot.T,
            turn(self.wood),
            turn(self.trunk),
            self.envelope_m3,
            self.young,
            None if self.reference is None else self.reference @ rot.T,
            dict(self.info),
        )


def log_uniform(rng: np.random.Generator, low: float, high: float) -> float:
    """A value drawn log-uniformly between ``low`` and ``high``."""
    return float(np.exp(rng.uniform(np.log(low), np.log(high))))


def sample_mesh(
    verts: np.ndarray, faces: np.ndarray, density: float, rng: np.random.Generator
) -> np.ndarray:
    """Every vertex used by ``faces`` and ``density`` uniform points per m² of their area."""
    verts, faces = np.asarray(verts, float), np.asarray(faces)
    if len(faces) == 0:
        return np.empty((0, 3))
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    count = rng.poisson(area * density)
    tri = np.repeat(np.arange(len(faces)), count)
    u, v = rng.random(len(tri)), rng.random(len(tri))
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    inner = a[tri] + u[:, None] * (b[tri] - a[tri]) + v[:, None] * (c[tri] - a[tri])
    return np.concatenate([verts[np.unique(faces)], inner])


def from_orchard_tree(tree, spec, rng: np.random.Generator) -> Specimen:
    """A tree of the orchard simulator (:class:`canopy_kit.sim.orchard.Tree`) as a specimen
    of the ``envelope`` family, moved so its trunk base is at the origin."""
    from canopy_kit.sim.scene import leaf_cluster_vertices, wood_parts

    shell, core = spec.foliage_density_shell, spec.foliage_density_core
    if tree.foliage_scale != 1.0:
        shell, core = shell * tree.foliage_scale, core * tree.foliage_scale
    leaves = leaf_cluster_vertices(
        tree, rng, shell, core, spec.leaf_cluster_size_range, spec.leaf_penetration_m
    )
    base = np.asarray(tree.base, float)
    parts = wood_parts(tree)
    crown = [(v - base, f) for v, f, inside in parts if inside]
    trunk = [(v - base, f) for v, f, inside in parts if not inside]
    return Specimen(
        f"{tree.crown_form}-{tree.tree_id}",
        "envelope",
        tree.crown_form,
        leaves - base,
        joined(crown),
        joined(trunk),
        envelope_m3=float(tree.crown.volume),
        young=tree.crown_form == "sparse",
    )


def joined(meshes: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Meshes (vertices, faces indexing their own vertices) as one mesh."""
    if not meshes:
        return EMPTY_MESH
    offsets = np.cumsum([0] + [len(v) for v, _ in meshes[:-1]])
    verts = np.concatenate([np.asarray(v, float) for v, _ in meshes])
    faces = np.concatenate([np.asarray(f) + o for (_, f), o in zip(meshes, offsets)])
    return verts, faces.astype(np.int64)
