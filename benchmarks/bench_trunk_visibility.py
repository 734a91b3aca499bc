"""Could drone photos seed touching crowns with their trunks? Per flight pattern and gimbal
pitch, how many trees' trunks a planned flight sees under the crowns (no rendering, no SfM).

    .venv/bin/python benchmarks/bench_trunk_visibility.py --orchard almond --seed 61
    .venv/bin/python benchmarks/bench_trunk_visibility.py --orchard pistachio --flights double-grid:-60 orbit:-35

A trunk (its mid-stem point) counts as seen in a photo when it projects inside the image and
the straight ray to it passes through no crown envelope of the simulator's truth (envelopes
taken as opaque; the rendered foliage has gaps a ray may pass through, so a few more trunks
may show in the photos). Prints per flight: photos, trees, trunks seen by at least one and at
least three photos.
"""

from __future__ import annotations

import argparse

import numpy as np


def seen_by(orchard, shots, point: np.ndarray, near_m: float = 12.0) -> int:
    """How many planned photos see ``point`` with no crown envelope on the ray to it."""
    crowns = [
        t.crown for t in orchard.trees if np.hypot(*(np.array(t.base[:2]) - point[:2])) < near_m
    ]
    top = max(c.z_range[1] for c in crowns) + 0.1
    n = 0
    for shot in shots:
        view = shot.view
        cam = view.rotation.T @ (point - view.position)
        if cam[2] <= 0:
            continue
        u = view.focal_px * cam[0] / cam[2] + view.width / 2
        v = view.focal_px * cam[1] / cam[2] + view.height / 2
        if not (0 <= u < view.width and 0 <= v < view.height):
            continue
        ray = point - view.position
        length = float(np.linalg.norm(ray))
        samples = view.position + np.outer(np.arange(0.0, length - 0.15, 0.05) / length, ray)
        samples = samples[samples[:, 2] < top]  # only below the canopy's top can a crown hide it
        n += not any(c.contains(samples).any() for c in crowns)
    return n


def main() -> None:
    from canopy_kit.sim import load_sim_config
    from canopy_kit.sim.drone import plan_shots
    from canopy_kit.sim.session import build_world

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--orchard", default="almond")
    parser.add_argument("--seed", type=int, default=61)
    parser.add_argument("--rows", type=int, default=4)
    parser.add_argument("--trees", type=int, default=8)
    parser.add_argument(
        "--flights",
        nargs="+",
        default=["double-grid:-60", "double-grid:-45", "double-grid:-35", "orbit:-45", "orbit:-35"],
        help="PATTERN:PITCH (pitch in degrees; -35 is the lowest whose image top stays 5 deg below the horizon)",
    )
    args = parser.parse_args()
    for flight in args.flights:
        pattern, pitch = flight.split(":")
        drone = {"enabled": True, "pattern": pattern, "gimbal_pitch_deg": float(pitch)}
        orchard_spec = {"rows": args.rows, "trees_per_row": args.trees}
        config = load_sim_config(
            args.orchard, {"seed": args.seed, "orchard": orchard_spec, "drone": drone}
        )
        orchard, *_ = build_world(config)
        shots = plan_shots(orchard, config.drone, np.random.default_rng(0))
        counts = np.array(
            [
                seen_by(orchard, shots, np.array(t.base) + 0.5 * (np.array(t.trunk_top) - t.base))
                for t in orchard.trees
            ]
        )
        print(
            f"{args.orchard} seed {args.seed} {pattern} pitch {pitch}: {len(shots)} photos, "
            f"{len(counts)} trees, trunks seen by >= 1 photo {(counts >= 1).sum()}, "
            f"by >= 3 {(counts >= 3).sum()}",
            flush=True,
        )


if __name__ == "__main__":
    main()
