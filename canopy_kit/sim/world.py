"""The simulator's world model of a session it wrote (:class:`canopy_kit.evaluate.truth.WorldModel`).

Evaluation asks :meth:`canopy_kit.evaluate.truth.SessionTruth.world` for exact geometry; the truth
module names this class for folders holding ``truth/sim_config.toml``, so stages reach
the simulator's geometry without importing it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from canopy_kit.sim.orchard import Orchard
from canopy_kit.sim.scene import Scene
from canopy_kit.sim.specimen import COMPLETE_DENSITY


class SimulatedWorld:
    """The orchard and scene of a simulated session, rebuilt from its stored config and seed."""

    def __init__(self, session_dir: str | Path) -> None:
        self.root = Path(session_dir)

    def orchard(self) -> Orchard:
        """The exact orchard (crown envelopes, terrain)."""
        from canopy_kit.sim.session import regenerate_orchard

        return regenerate_orchard(self.root)

    def scene(self) -> Scene:
        """The scene the LiDAR saw (its surfaces give map-to-surface distances)."""
        from canopy_kit.sim.session import build_world, load_sim_config_of

        return build_world(load_sim_config_of(self.root))[2]

    def complete_foliage(self, density: float = COMPLETE_DENSITY) -> dict[int, np.ndarray]:
        """Per tree id: ``density`` points per m² on every leaf and crown-branch surface the
        scene gives the tree (every vertex too), seen or not: the complete foliage."""
        from canopy_kit.sim.specimen import sample_mesh

        scene = self.scene()
        rng = np.random.default_rng(0)
        out = {}
        for tree in np.unique(scene.tree_id[scene.tree_id >= 0]):
            faces = scene.triangles[scene.tree_id == tree]
            out[int(tree)] = sample_mesh(scene.vertices, faces, density, rng)
        return out
