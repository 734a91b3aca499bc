"""Side and top sections of one tree of each simulator crown form (docs/figures/sim_crown_forms.png).

    .venv/bin/python scripts/crown_forms_figure.py [--out docs/figures] [--seed 2]

Top row: the envelope's vertical section across the row through the crown centre (the
outline), with the leaf clusters of a 0.3 m slab around it (dots), the trunk and the
envelope's centre (+). Bottom row: the horizontal section 0.4 m above the centre.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from canopy_kit.sim.config import load_sim_config
from canopy_kit.sim.orchard import generate_orchard
from canopy_kit.sim.scene import FOLIAGE, build_scene

FORMS = ["ellipsoid", "lobed", "vase", "hedged", "sparse"]


def _section(crown, e1: np.ndarray, e2: np.ndarray, origin: np.ndarray, n: int = 720) -> np.ndarray:
    """Outline of the envelope in the plane ``origin + s e1 + t e2`` (rays from the plane's
    foot of the centre; exact for planes through the centre, a good picture otherwise)."""
    ang = np.linspace(0, 2 * np.pi, n)
    out = []
    for a in ang:
        d = np.cos(a) * e1 + np.sin(a) * e2
        ts = np.linspace(0, 6, 1200)
        p = origin + ts[:, None] * d
        inside = crown.contains(p)
        k = np.nonzero(inside)[0]
        out.append(ts[k.max()] if len(k) else 0.0)
    r = np.asarray(out)
    return np.column_stack([r * np.cos(ang), r * np.sin(ang)])


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", type=Path, default=Path("docs/figures"))
    parser.add_argument("--seed", type=int, default=2)
    args = parser.parse_args()
    fig, axes = plt.subplots(2, len(FORMS), figsize=(3.2 * len(FORMS), 6.4))
    for k, form in enumerate(FORMS):
        cfg = load_sim_config(
            "pistachio",
            {
                "orchard": {
                    "rows": 1,
                    "trees_per_row": 1,
                    "crown_form": form,
                    "leaf_penetration_m": 0.5,
                }
            },
        )
        rng = np.random.default_rng(args.seed)
        orchard = generate_orchard(cfg.orchard, rng)
        scene = build_scene(orchard, rng)
        tree = orchard.trees[0]
        c = np.asarray(tree.crown.center)
        along = np.append(orchard.row_direction, 0.0)
        across = np.append(orchard.right_direction, 0.0)
        up = np.array([0.0, 0.0, 1.0])
        ax = axes[0, k]
        tri = (scene.material == FOLIAGE) & (scene.tree_id == tree.tree_id)
        leaves = scene.vertices[scene.triangles[tri]].mean(axis=1) - c
        slab = np.abs(leaves @ along) < 0.15
        ax.scatter(leaves[slab] @ across, leaves[slab] @ up + c[2], s=2, c="tab:green", alpha=0.6)
        outline = _section(tree.crown, across, up, c)
        ax.plot(outline[:, 0], outline[:, 1] + c[2], "k-", lw=1.2)
        base = np.asarray(tree.base) - c
        top = np.asarray(tree.trunk_top) - c
        ax.plot(
            [base @ across, top @ across],
            [tree.base[2], tree.trunk_top[2]],
            color="saddlebrown",
            lw=3,
        )
        ax.plot([0], [c[2]], "r+", ms=10)
        ax.set_title(f"{form}: {tree.crown.volume:.1f} m³")
        ax.set_xlabel("across row (m)")
        ax.set_aspect("equal")
        ax.set_xlim(-3, 3)
        ax.set_ylim(0, 5)
        ax2 = axes[1, k]
        outline = _section(tree.crown, along, across, c + np.array([0, 0, 0.4]))
        ax2.fill(outline[:, 0], outline[:, 1], color="tab:green", alpha=0.4)
        ax2.plot(outline[:, 0], outline[:, 1], "k-", lw=1)
        ax2.set_aspect("equal")
        ax2.set_xlim(-3, 3)
        ax2.set_ylim(-3, 3)
        ax2.set_xlabel("along row (m)")
        if k == 0:
            ax.set_ylabel("height (m)")
            ax2.set_ylabel("across row (m), 0.4 m above centre")
    fig.tight_layout()
    args.out.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out / "sim_crown_forms.png", dpi=90)


if __name__ == "__main__":
    main()
