"""A row of specimens in a simulated alley, driven past by one of the simulator's LiDARs.

Any tree the simulator can mesh (:class:`canopy_kit.sim.specimen.Specimen`: the orchard's
envelope crowns, lobe unions, grown trees, real clouds made into splats) is planted along a
row on flat ground, the row along x, trunks at y = 0. The sensor (a model of
``canopy_kit.sim.config.SENSOR_MODELS``) drives straight along the alley on either side of
the row (``left``: y > 0) at walking-robot speed; every return is labelled with the tree
whose leaf or crown branch it hit (the trunk below the crown and the ground are -1). Points
are in the world frame at their firing time, with the sensor's range noise and dropouts:
what a drive maps with perfect poses, before any segmentation.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from canopy_kit.sim.specimen import Specimen

SIDES = ("left", "right")
Progress = Callable[[str, float, float], None]


class StraightPass:
    """A constant-speed, level drive from ``start`` to ``end`` (x, y) at ``height``; the
    interface of :class:`canopy_kit.sim.trajectory.Trajectory` that the LiDAR uses."""

    def __init__(
        self, start: Sequence[float], end: Sequence[float], height: float, speed: float
    ) -> None:
        self.start = np.array([start[0], start[1], height], float)
        self.end = np.array([end[0], end[1], height], float)
        length = float(np.linalg.norm(self.end - self.start))
        self.start_time, self.end_time = 0.0, length / speed
        self.yaw = float(np.arctan2(*(self.end - self.start)[1::-1]))

    def poses(self, times: np.ndarray):
        """Positions (N, 3) and orientations (a scipy Rotation) at ``times``."""
        from scipy.spatial.transform import Rotation

        times = np.atleast_1d(np.asarray(times, float))
        f = np.clip((times - self.start_time) / (self.end_time - self.start_time), 0.0, 1.0)
        pos = self.start + f[:, None] * (self.end - self.start)
        return pos, Rotation.from_euler("z", np.full((len(times), 1), self.yaw))


@dataclass
class AlleyScan:
    """The returns of one drive per side: world points and the index of the tree each hit
    (-1: ground or trunk), and where the trees stand (x along the row)."""

    specimens: list[Specimen]
    positions: np.ndarray  # (K, 2): each trunk base's x (along the row) and y
    points: dict[str, np.ndarray]
    tree: dict[str, np.ndarray]
    sensor: str
    mount_height: float
    alley_offset: float

    def tree_points(self, k: int, sides: Sequence[str] = SIDES) -> np.ndarray:
        """Tree ``k``'s returns from the drives on ``sides``, in the tree's own frame (its trunk
        base at the origin, as its specimen and :meth:`Specimen.complete_foliage` are)."""
        parts = [self.points[s][self.tree[s] == k] for s in sides if s in self.points]
        xyz = np.concatenate(parts) if parts else np.empty((0, 3))
        return xyz - np.array([*self.positions[k], 0.0])


def plant_row(specimens: Sequence[Specimen], gaps: Sequence[float] | float) -> np.ndarray:
    """Trunk positions (K, 2) along the row line y = 0, ``gaps`` metres apart (one value or
    one per gap)."""
    n = len(specimens)
    gaps = np.broadcast_to(np.asarray(gaps, float), (max(n - 1, 0),))
    x = np.concatenate([[0.0], np.cumsum(gaps)])
    return np.column_stack([x, np.zeros_like(x)])


def row_scene(specimens: Sequence[Specimen], positions: np.ndarray, margin: float = 30.0):
    """The scene: flat ground, and each specimen's crown (its index) and trunk (-1)."""
    from canopy_kit.sim.scene import FOLIAGE, GROUND, WOOD, SceneBuilder, octahedra_faces

    b = SceneBuilder()
    x0, x1 = float(positions[:, 0].min()) - margin, float(positions[:, 0].max()) + margin
    ground = np.array(
        [[x0, -margin, 0.0], [x1, -margin, 0.0], [x1, margin, 0.0], [x0, margin, 0.0]]
    )
    b.add(ground, np.array([[0, 1, 2], [0, 2, 3]]), GROUND, -1)
    rng = np.random.default_rng(0)  # shades only: returns do not depend on them
    top = 0.0
    for k, (sp, xy) in enumerate(zip(specimens, positions)):
        shift = np.array([xy[0], xy[1], 0.0])
        m = sp.n_leaf_clusters
        if m:
            b.add(
                sp.leaves + shift,
                octahedra_faces(m),
                FOLIAGE,
                k,
                np.repeat(rng.uniform(0.6, 1.4, m), 8),
            )
        for mesh, tree in ((sp.wood, k), (sp.trunk, -1)):
            if len(mesh[1]):
                b.add(np.asarray(mesh[0]) + shift, np.asarray(mesh[1]), WOOD, tree)
        top = max(top, float(sp.extent()[1][2]))
    return b.build((np.array([x0, -margin, -1.0]), np.array([x1, margin, top + 1.0])))


def drive_row(
    specimens: Sequence[Specimen],
    gaps: Sequence[float] | float,
    sensor: str = "vlp16",
    sides: Sequence[str] = SIDES,
    mount_height: float = 1.8,
    clearance: float = 1.2,
    min_alley_offset: float = 2.5,
    speed: float = 1.5,
    lead: float = 6.0,
    seed: int = 0,
    progress: Progress | None = None,
    positions: np.ndarray | None = None,
) -> AlleyScan:
    """Drive ``sensor`` along the alley on each of ``sides`` of a row of ``specimens``.

    The alley's centre line lies ``clearance`` metres beyond the widest crown's side (at least
    ``min_alley_offset`` from the row line); each pass starts ``lead`` metres before the first
    trunk and ends as far past the last. ``positions`` (K, 2): trunk positions instead of a
    row (a plot of trees standing where they stood, around y = 0); ``gaps`` is then unused.
    """
    from canopy_kit.config import from_dict
    from canopy_kit.sim.config import SENSOR_MODELS, LidarSpec
    from canopy_kit.sim.lidar import SpinningLidar

    if sensor not in SENSOR_MODELS:
        raise ValueError(f"sensor {sensor!r} is not one of {', '.join(SENSOR_MODELS)}")
    bad = [s for s in sides if s not in SIDES]
    if bad:
        raise ValueError(f"sides must be among {SIDES}, got {bad}")
    positions = plant_row(specimens, gaps) if positions is None else np.asarray(positions, float)
    half_width = max(
        float(np.abs(np.stack(sp.extent())[:, 1] + y).max())
        for sp, y in zip(specimens, positions[:, 1])
    )
    offset = max(half_width + clearance, min_alley_offset)
    scene = row_scene(specimens, positions)
    spec = from_dict(LidarSpec, {**SENSOR_MODELS[sensor], "mount_height": mount_height}, "lidar")
    rng = np.random.default_rng(seed)
    points, trees = {}, {}
    x0, x1 = float(positions[:, 0].min()) - lead, float(positions[:, 0].max()) + lead
    for n_side, side in enumerate(sides):
        y = offset if side == "left" else -offset
        start, end = ((x0, y), (x1, y)) if side == "left" else ((x1, y), (x0, y))
        lidar = SpinningLidar(spec, scene, StraightPass(start, end, mount_height, speed), rng)
        stamps = lidar.sweep_times()
        xyz, prim = [], []
        for i, stamp in enumerate(stamps):
            p, pr = lidar.sweep_world(float(stamp))
            xyz.append(p)
            prim.append(pr)
            if progress:
                progress(f"drive {side}", n_side * len(stamps) + i + 1, len(sides) * len(stamps))
        xyz = np.concatenate(xyz)
        tree = scene.tree_id[np.concatenate(prim)]
        points[side], trees[side] = xyz[tree >= 0], tree[tree >= 0]
    return AlleyScan(list(specimens), positions, points, trees, sensor, mount_height, offset)
