"""Make the simulator figures in docs/figures (top views, one scan by time).

.venv/bin/python scripts/sim_figures.py [--out docs/figures]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from canopy_kit.io.bag import open_bag
from canopy_kit.sim import load_sim_config, simulate_session
from canopy_kit.sim.plots import plot_orchard_top_view, plot_scan_by_time
from canopy_kit.sim.session import build_world


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", type=Path, default=Path("docs/figures"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(14, 8))
    for ax, kind in zip(axes, ("pistachio", "almond")):
        cfg = load_sim_config(kind, {"orchard": {"rows": 4, "trees_per_row": 8}, "seed": 1})
        orchard, trajectory, _, _ = build_world(cfg)
        t = np.linspace(trajectory.start_time, trajectory.end_time, 4000)
        plot_orchard_top_view(orchard, ax, trajectory.poses(t)[0])
    fig.tight_layout()
    fig.savefig(args.out / "sim_orchards_top.png", dpi=110)
    with tempfile.TemporaryDirectory() as tmp:
        cfg = load_sim_config(
            "pistachio", {"orchard": {"rows": 2, "trees_per_row": 4}, "drive": {"alleys": "inner"}}
        )
        session = simulate_session(Path(tmp) / "s", cfg)
        with open_bag(session.bag) as bag:
            for scan in bag.scans():
                if scan.index == 150:
                    break
        fig, ax = plt.subplots(figsize=(7, 6))
        plot_scan_by_time(scan.xyz, scan.times, ax)
        fig.tight_layout()
        fig.savefig(args.out / "sim_scan_time.png", dpi=110)
    print(f"wrote {args.out}/sim_orchards_top.png and sim_scan_time.png")


if __name__ == "__main__":
    main()
