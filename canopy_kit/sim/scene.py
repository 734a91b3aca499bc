"""Triangle scene of an orchard for ray casting: ground, grass, trunks, branches, foliage.

Foliage is many small leaf clusters (flattened octahedra) placed inside each crown
envelope, denser towards the shell, so beams pass into and sometimes through a crown.
Every triangle carries a material, the tree it belongs to (-1 for ground, grass and
trunks below the crown; ``TRELLIS_ID``, -2, for a fruiting wall's posts, wires and drip
line) and a shade factor for rendering.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from canopy_kit.core.extras import needs_extra
from canopy_kit.sim.orchard import Orchard, Tree
from canopy_kit.sim.trellis import TRELLIS_ID, trellis_cylinders

GROUND, GRASS, WOOD, FOLIAGE, TRELLIS = 0, 1, 2, 3, 4
MATERIAL_NAMES = {
    GROUND: "ground",
    GRASS: "grass",
    WOOD: "wood",
    FOLIAGE: "foliage",
    TRELLIS: "trellis",
}

_OCTAHEDRON_V = np.array(
    [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float
)
_OCTAHEDRON_F = np.array(
    [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
)


@dataclass
class Scene:
    """A triangle soup with per-triangle attributes."""

    vertices: np.ndarray  # (V, 3) float64
    triangles: np.ndarray  # (T, 3) int64
    material: np.ndarray  # (T,) uint8
    tree_id: np.ndarray  # (T,) int32
    shade: np.ndarray  # (T,) float32, per-triangle colour variation in [0.6, 1.4]
    bounds: tuple[np.ndarray, np.ndarray]

    def raycasting_scene(self):
        """An Open3D RaycastingScene holding the triangles (geometry id 0)."""
        with needs_extra("open3d"):
            import open3d as o3d

        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(
            o3d.core.Tensor(self.vertices.astype(np.float32)),
            o3d.core.Tensor(self.triangles.astype(np.uint32)),
        )
        return scene


class SceneBuilder:
    """Collects meshes with their material, tree and shade, then builds one :class:`Scene`."""

    def __init__(self) -> None:
        self.v: list[np.ndarray] = []
        self.f: list[np.ndarray] = []
        self.mat: list[np.ndarray] = []
        self.tid: list[np.ndarray] = []
        self.shade: list[np.ndarray] = []
        self.n = 0

    def add(
        self,
        verts: np.ndarray,
        faces: np.ndarray,
        material: int,
        tree: np.ndarray | int,
        shade: np.ndarray | float = 1.0,
    ) -> None:
        """Add a mesh whose faces index ``verts``; ``tree`` per face or for all."""
        self.v.append(verts)
        self.f.append(faces + self.n)
        self.n += len(verts)
        m = len(faces)
        self.mat.append(np.full(m, material, np.uint8))
        self.tid.append(np.broadcast_to(np.asarray(tree, np.int32), (m,)).copy())
        self.shade.append(np.broadcast_to(np.asarray(shade, np.float32), (m,)).copy())

    def build(self, bounds: tuple[np.ndarray, np.ndarray]) -> Scene:
        """The scene of everything added, with these bounds."""
        return Scene(
            np.concatenate(self.v),
            np.concatenate(self.f),
            np.concatenate(self.mat),
            np.concatenate(self.tid),
            np.concatenate(self.shade),
            bounds,
        )


def build_scene(
    orchard: Orchard,
    rng: np.random.Generator,
    extra_bounds: tuple[np.ndarray, np.ndarray] | None = None,
    ground_step: float = 0.5,
) -> Scene:
    """Mesh the whole orchard; ``extra_bounds`` widens the ground (e.g. to the drive path)."""
    spec = orchard.spec
    lo, hi = _ground_bounds(orchard, extra_bounds)
    b = SceneBuilder()
    _add_ground(b, orchard, lo, hi, ground_step)
    _add_grass(b, orchard, rng, lo, hi)
    for tree in orchard.trees:
        _add_wood(b, tree)
        shell, core = spec.foliage_density_shell, spec.foliage_density_core
        if tree.foliage_scale != 1.0:
            shell, core = shell * tree.foliage_scale, core * tree.foliage_scale
        verts = leaf_cluster_vertices(
            tree, rng, shell, core, spec.leaf_cluster_size_range, spec.leaf_penetration_m
        )
        _add_leaf_clusters(b, tree, verts, rng)
    _add_trellis(b, orchard)
    top = max((t.crown.z_range[1] for t in orchard.trees), default=5.0)
    top = max([top, *(float(t.post_tops[:, 2].max()) for t in orchard.trellis)])
    return b.build((np.array([lo[0], lo[1], -50.0]), np.array([hi[0], hi[1], top + 1.0])))


def _ground_bounds(
    orchard: Orchard, extra: tuple[np.ndarray, np.ndarray] | None
) -> tuple[np.ndarray, np.ndarray]:
    spec = orchard.spec
    pts = [np.asarray(t.base[:2]) for t in orchard.trees]
    a0, a1 = orchard.along_range
    corners = orchard.to_local(
        np.array([a0 - spec.headland, a0 - spec.headland, a1 + spec.headland, a1 + spec.headland]),
        np.array([-spec.row_spacing, orchard.row_offsets[-1] + spec.row_spacing] * 2),
    )
    pts.extend(corners)
    pts = np.asarray(pts)
    lo, hi = pts.min(axis=0) - spec.margin, pts.max(axis=0) + spec.margin
    if extra is not None:
        lo = np.minimum(lo, np.asarray(extra[0])[:2] - spec.margin)
        hi = np.maximum(hi, np.asarray(extra[1])[:2] + spec.margin)
    return lo, hi


def _add_ground(
    b: SceneBuilder, orchard: Orchard, lo: np.ndarray, hi: np.ndarray, step: float
) -> None:
    xs = np.arange(lo[0], hi[0] + step, step)
    ys = np.arange(lo[1], hi[1] + step, step)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    gz = orchard.terrain.height(gx, gy)
    verts = np.column_stack([gx.ravel(), gy.ravel(), gz.ravel()])
    nx, ny = gx.shape
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, bb = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.column_stack([a, bb, c]), np.column_stack([a, c, d])])
    b.add(verts, faces, GROUND, -1)


def _add_grass(
    b: SceneBuilder, orchard: Orchard, rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray
) -> None:
    spec = orchard.spec
    if spec.grass_height <= 0 or spec.grass_density <= 0:
        return
    n = int(spec.grass_density * np.prod(hi - lo))
    xy = rng.uniform(lo, hi, (n, 2))
    z = orchard.terrain.height(xy[:, 0], xy[:, 1])
    h = spec.grass_height * rng.uniform(0.3, 1.0, n)
    ang = rng.uniform(0, np.pi, n)
    w = 0.08 * rng.uniform(0.6, 1.4, n)
    verts, faces = [], []
    for k, extra in enumerate((0.0, np.pi / 2)):
        dx, dy = np.cos(ang + extra) * w, np.sin(ang + extra) * w
        tip = np.column_stack(
            [xy[:, 0] + rng.normal(0, 0.03, n), xy[:, 1] + rng.normal(0, 0.03, n), z + h]
        )
        left = np.column_stack([xy[:, 0] - dx, xy[:, 1] - dy, z - 0.02])
        rightp = np.column_stack([xy[:, 0] + dx, xy[:, 1] + dy, z - 0.02])
        v = np.stack([left, rightp, tip], axis=1).reshape(-1, 3)
        verts.append(v)
        faces.append(np.arange(3 * n).reshape(n, 3) + k * 3 * n)
    b.add(np.concatenate(verts), np.concatenate(faces), GRASS, -1, rng.uniform(0.7, 1.3, 2 * n))


def cylinder(
    p0: np.ndarray, p1: np.ndarray, r0: float, r1: float, sides: int = 8
) -> tuple[np.ndarray, np.ndarray]:
    """An open tapered cylinder between two points."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    return cylinders(p0[None], p1[None], np.array([r0], float), np.array([r1], float), sides)


def cylinders(
    p0: np.ndarray, p1: np.ndarray, r0: np.ndarray, r1: np.ndarray, sides: int = 8
) -> tuple[np.ndarray, np.ndarray]:
    """Open tapered cylinders from ``p0[k]`` (radius ``r0[k]``) to ``p1[k]`` (``r1[k]``), as one
    mesh: ``(2 · sides · K, 3)`` vertices and ``(2 · sides · K, 3)`` faces."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    axis = p1 - p0
    axis /= np.linalg.norm(axis, axis=1)[:, None]
    helper = np.where(np.abs(axis[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u, axis=1)[:, None]
    v = np.cross(axis, u)
    ang = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    ring = np.cos(ang)[None, :, None] * u[:, None, :] + np.sin(ang)[None, :, None] * v[:, None, :]
    r0 = np.asarray(r0, float)[:, None, None]
    r1 = np.asarray(r1, float)[:, None, None]
    verts = np.concatenate([p0[:, None, :] + r0 * ring, p1[:, None, :] + r1 * ring], axis=1)
    i = np.arange(sides)
    j = (i + 1) % sides
    one = np.concatenate(
        [np.column_stack([i, j, j + sides]), np.column_stack([i, j + sides, i + sides])]
    )
    faces = one[None, :, :] + 2 * sides * np.arange(len(p0))[:, None, None]
    return verts.reshape(-1, 3), faces.reshape(-1, 3)


def _add_trellis(b: SceneBuilder, orchard: Orchard) -> None:
    """Posts, wires and drip lines (``canopy_kit.sim.trellis``): never canopy."""
    for p0, p1, radius in trellis_cylinders(orchard.trellis):
        verts, faces = cylinders(p0, p1, radius, radius, sides=8)
        b.add(verts, faces, TRELLIS, TRELLIS_ID)


def _add_wood(b: SceneBuilder, tree: Tree) -> None:
    for verts, faces, in_crown in wood_parts(tree):
        b.add(verts, faces, WOOD, tree.tree_id if in_crown else -1)


def _frames_about(normals: np.ndarray, spin: np.ndarray) -> np.ndarray:
    """Rotation matrices (m, 3, 3) taking z to each normal, turned by ``spin`` about it."""
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    u = np.cross(normals, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(normals, u)
    c, s = np.cos(spin)[:, None], np.sin(spin)[:, None]
    u, v = c * u + s * v, -s * u + c * v
    return np.stack([u, v, normals], axis=2)


def wood_parts(tree: Tree) -> list[tuple[np.ndarray, np.ndarray, bool]]:
    """The tree's trunk and scaffold branches as meshes (vertices, faces, inside the crown):
    the trunk below the crown is not canopy, the part inside it and the branches are."""
    base = np.asarray(tree.base) - np.array([0, 0, 0.1])
    top = np.asarray(tree.trunk_top)
    crown_bottom = tree.crown.z_range[0]
    parts = []
    if crown_bottom > base[2] + 0.2 and crown_bottom < top[2]:
        f = (crown_bottom - base[2]) / (top[2] - base[2])
        mid = base + f * (top - base)
        r_mid = tree.trunk_radius * (1 - 0.3 * f)
        parts.append((*cylinder(base, mid, tree.trunk_radius, r_mid), False))
        parts.append((*cylinder(mid, top, r_mid, tree.trunk_radius * 0.7), True))
    else:
        parts.append((*cylinder(base, top, tree.trunk_radius, tree.trunk_radius * 0.7), False))
    for tip in tree.branch_tips:
        parts.append(
            (*cylinder(top, np.asarray(tip), tree.trunk_radius * 0.45, 0.015, sides=6), True)
        )
    return parts


def _add_leaf_clusters(
    b: SceneBuilder, tree: Tree, verts: np.ndarray, rng: np.random.Generator
) -> None:
    """Mesh ``leaf_cluster_vertices`` as octahedra, each with a drawn shade."""
    add_octahedra(b, verts, tree.tree_id, rng)


def octahedra_faces(m: int) -> np.ndarray:
    """The faces (8 m, 3) of ``m`` octahedra whose vertices come six by six."""
    return (_OCTAHEDRON_F[None, :, :] + 6 * np.arange(m)[:, None, None]).reshape(-1, 3)


def add_octahedra(
    b: SceneBuilder, verts: np.ndarray, tree: int, rng: np.random.Generator, material: int = FOLIAGE
) -> None:
    """Add leaf clusters (vertices from :func:`leaf_octahedra`, six each) with drawn shades."""
    m = len(verts) // 6
    if m == 0:
        return
    shade = np.repeat(rng.uniform(0.6, 1.4, m), 8)
    b.add(verts, octahedra_faces(m), material, tree, shade)


def leaf_octahedra(
    centres: np.ndarray,
    size: np.ndarray,
    rng: np.random.Generator,
    normals: np.ndarray | None = None,
) -> np.ndarray:
    """The six vertices of flattened, randomly turned octahedra (``(6 m, 3)``): leaf clusters
    of diameter ``size`` (m) about ``centres``, 0.6-1.0 × as wide and 0.25-0.5 × as thick.
    ``normals``: unit vectors the thin axis of each takes (splats lying in a scanned
    surface), turned at random about them; None: turned at random in every way."""
    from scipy.spatial.transform import Rotation

    m = len(centres)
    if m == 0:
        return np.empty((0, 3))
    if normals is None:
        rot = Rotation.random(m, random_state=rng).as_matrix()
    else:
        rot = _frames_about(np.asarray(normals, float), rng.uniform(0, 2 * np.pi, m))
    scale = np.column_stack(
        [size, size * rng.uniform(0.6, 1.0, m), size * rng.uniform(0.25, 0.5, m)]
    )
    local = _OCTAHEDRON_V[None, :, :] * scale[:, None, :]
    return (centres[:, None, :] + np.einsum("mij,mkj->mki", rot, local)).reshape(-1, 3)


def leaf_cluster_vertices(
    tree: Tree,
    rng: np.random.Generator,
    shell: float,
    core: float,
    size_range: list[float],
    penetration: float = float("inf"),
) -> np.ndarray:
    """The six vertices of each leaf cluster (flattened octahedra, ``(6 m, 3)``) of one crown.

    Clusters lie inside the envelope, denser towards it by relative depth (from the
    envelope's centre, which for a vase is the trunk top), and at most ``penetration``
    metres below the envelope along the ray from the centre; vertices sticking out are
    moved radially back onto the envelope.
    """
    lo, hi = tree.crown.bounds
    n_candidates = int(shell * np.prod(hi - lo))
    p = rng.uniform(lo, hi, (n_candidates, 3))
    size = rng.uniform(size_range[0], size_range[1], n_candidates)
    depth = tree.crown.relative_depth(p)
    keep_prob = (core + (shell - core) * np.clip(depth, 0, 1) ** 3) / shell
    keep = (depth <= 1.0) & (rng.random(n_candidates) < keep_prob)
    if np.isfinite(penetration):
        keep &= depth_below_envelope(tree.crown, p, depth) <= penetration
    p, size = p[keep], size[keep]
    if len(p) == 0:
        return np.empty((0, 3))
    verts = leaf_octahedra(p, size, rng)
    # Clip leaf vertices that stick out radially back onto the envelope, so the foliage
    # fills the crown right up to its envelope and never beyond it.
    return _clip_to_envelope(tree.crown, verts)


def depth_below_envelope(
    crown,
    points: np.ndarray,
    relative: np.ndarray | None = None,
) -> np.ndarray:
    """``r(u) - |p - c|``: metres below the envelope along the ray from its centre (<0 outside)."""
    rho = np.linalg.norm(np.asarray(points, float) - np.asarray(crown.center), axis=1)
    rel = crown.relative_depth(points) if relative is None else relative
    out = np.full(len(rho), np.inf)
    nz = rel > 0
    out[nz] = rho[nz] / rel[nz] - rho[nz]
    return out


def _clip_to_envelope(crown, verts: np.ndarray) -> np.ndarray:
    """Move vertices outside the envelope radially onto it."""
    depth = crown.relative_depth(verts)
    out = depth > 1.0
    c = np.asarray(crown.center)
    verts = verts.copy()
    verts[out] = c + (verts[out] - c) / depth[out, None]
    return verts
