"""The hull's outline rule on rendered flights, from the simulator's truth alone: per crown,
how much of a round crown of its size the flight's exact silhouettes would let into the ring
the outline margin adds (``ground_truth.visual_hull.outline_excess``; the rule grows an
outline when this is at most ``HullOptions.max_outline_excess``).

    .venv/bin/python benchmarks/bench_outline_excess.py FLIGHT [FLIGHT ...]

A FLIGHT is a rendered drone session (``truth/drone_cameras.csv`` and ``truth/trees.csv``,
e.g. from ``bench_hull_flights.py``); no SfM is run: the cameras are the true ones, each
crown a sphere of half its mean diameter at its centre. Prints per flight the photos, the
crowns, the excess's minimum, median and maximum (%) and how many crowns the rule would
hold back.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd


def main() -> None:
    from ground_truth.flight_accuracy import true_cameras
    from ground_truth.visual_hull import HullOptions, outline_excess

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("flights", nargs="+", type=Path)
    args = parser.parse_args()
    options = HullOptions()
    for root in args.flights:
        cameras = true_cameras(root / "truth" / "drone_cameras.csv")
        shapes = [(c.height, c.width) for c in cameras]
        trees = pd.read_csv(root / "truth" / "trees.csv")
        centres = np.column_stack(
            [
                trees["crown_x"],
                trees["crown_y"],
                trees["z_ground"] + trees["crown_base_height_m"] + trees["crown_height_m"] / 2,
            ]
        )
        radii = trees["crown_diameter_mean_m"].to_numpy() / 2
        margin = options.outline_margin_m
        excess = 100 * np.array(
            [outline_excess(cameras, shapes, c, r, margin, options) for c, r in zip(centres, radii)]
        )
        held = int((excess > 100 * options.max_outline_excess).sum())
        print(
            f"{root.name}: {len(cameras)} photos, {len(excess)} crowns, excess (%) min"
            f" {excess.min():.2f} median {np.median(excess):.2f} max {excess.max():.2f};"
            f" held back: {held}"
        )


if __name__ == "__main__":
    main()
