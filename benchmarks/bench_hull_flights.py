"""The visual hull in ``process_flight`` on held-out oblique flights: each aerial volume model
against the simulator's exact crown volume (``crown_volume_m3``), and the flight's time.

    .venv/bin/python benchmarks/bench_hull_flights.py --orchard pistachio --seed 51
    .venv/bin/python benchmarks/bench_hull_flights.py --orchard almond --seed 51
    .venv/bin/python benchmarks/bench_hull_flights.py --orchard pistachio --seed 52 --crown-form lobed

Renders (once, into ``--work``, default ``work/bench_hull``) a ``--rows`` x ``--trees`` flight
flown in ``--pattern`` (default 4 x 8, double grid; ``--crown-form``: the orchard's crown
form, default the preset's), processes it with the default
``[ground_truth]`` settings (crowns from the imagery alone, every core) and prints one JSON line:
crowns one-to-one with the true trees (within 1.5 m, crowns cut by the mosaic border left out),
each model's bias and MAPE over those crowns, the recommended model, and the wall and CPU time
per stage; the crowns whose outlines the hull grew (``hull_outlines``);
the crowns flagged from the imagery (``crown_flag``), how many of them hold two or
more true crown centres or none (``trees_per_crown``, the simulator's truth), and the hull's
bias and MAPE over the unflagged crowns alone. Run flights one at a time: each uses every core for minutes.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import pandas as pd

REPO = Path(__file__).resolve().parents[1]
MODELS = (
    "hull_volume_m3",
    "sphere_volume_m3",
    "ellipsoid_volume_m3",
    "envelope_volume_m3",
    "chm_volume_m3",
)


def flight_of_form(
    work: Path, kind: str, rows: int, trees: int, seed: int, pattern: str, form: str
) -> Path:
    """A rendered drone-only session (cached) of crowns of ``form``."""
    from canopy_kit.sim import load_sim_config
    from canopy_kit.sim.drone import simulate_drone_session

    root = work / f"{kind}_{form}_{rows}x{trees}_s{seed}_{pattern}"
    if not (root / "truth" / "drone_cameras.csv").exists():
        orchard = {"rows": rows, "trees_per_row": trees, "crown_form": form}
        drone = {"enabled": True, "pattern": pattern}
        cfg = load_sim_config(kind, {"seed": seed, "orchard": orchard, "drone": drone})
        simulate_drone_session(root, cfg)
    return root


def main() -> None:
    from bench_ground_truth import flight, frame_of

    from canopy_kit.evaluate.stats import agreement
    from ground_truth import process_flight
    from ground_truth.crown_flags import FLAG_COLUMN
    from ground_truth.flight_accuracy import crown_agreement, trees_per_crown

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=REPO / "work" / "bench_hull")
    parser.add_argument("--orchard", default="pistachio")
    parser.add_argument("--seed", type=int, default=51)
    parser.add_argument("--rows", type=int, default=4)
    parser.add_argument("--trees", type=int, default=8)
    parser.add_argument("--pattern", default="double-grid")
    parser.add_argument("--crown-form", help="the orchard's crown form (default: the preset's)")
    args = parser.parse_args()

    shape = (args.work, args.orchard, args.rows, args.trees, args.seed, args.pattern)
    root = flight_of_form(*shape, args.crown_form) if args.crown_form else flight(*shape)
    t0, c0 = time.perf_counter(), time.process_time()
    result = process_flight(root / "drone", root / "gt_imagery", frame=frame_of(root))
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    truth = pd.read_csv(root / "truth" / "trees.csv")
    table, m = crown_agreement(result.crowns, truth)
    models = {}
    for col in MODELS:
        known = table[col].notna()
        a = agreement(table.loc[known, col], table.loc[known, "volume_true_m3"])
        errors = (table.loc[known, col] / table.loc[known, "volume_true_m3"] - 1) * 100
        models[col] = {
            "n": int(known.sum()),
            "bias_pct": round(a.bias_pct, 1),
            "mape_pct": round(a.mape_pct, 1),
            "range_pct": [round(float(errors.min())), round(float(errors.max()))],
        }
    report = result.report
    flags = result.crowns[FLAG_COLUMN].fillna("")
    seg = result.segmentation
    inside = trees_per_crown(seg.labels, seg.grid, result.crowns, truth)
    inner = ~result.crowns["touches_border"].to_numpy(bool)
    flagged = (flags != "").to_numpy()
    _, m_kept = crown_agreement(result.crowns[flags == ""], truth)
    hull_kept = {
        "n": m_kept["matched"],
        "bias_pct": round(m_kept.get("volume_hull_aerial_bias_pct", float("nan")), 1),
        "mape_pct": round(m_kept.get("volume_hull_aerial_mape_pct", float("nan")), 1),
    }
    line = {
        "flight": root.name,
        "photos": report["sfm"]["total_images"],
        "registered": report["sfm"]["registered_images"],
        "trees": m["trees"],
        "crowns": m["crowns"],
        "one_to_one": m["matched"],
        "diameter_mae_m": round(m["diameter_mae_m"], 3),
        "flight_views": report["flight_views"],
        "aerial_volume_model": report["aerial_volume_model"]["recommended"],
        "hull_outlines": report.get("hull_outlines"),
        "models": models,
        "crown_flags": report["crown_flags"],
        "flagged": {
            "crowns": int(flagged.sum()),
            "of_them_two_trees": int((flagged & (inside >= 2)).sum()),
            "of_them_no_tree_centre": int((flagged & (inside == 0)).sum()),
            "of_them_one_tree": int((flagged & (inside == 1)).sum()),
            "inner_crowns_two_trees": int((inner & (inside >= 2)).sum()),
            "inner_crowns_no_tree_centre": int((inner & (inside == 0)).sum()),
            "flagged_ids": [int(i) for i in result.crowns.loc[flagged, "crown_id"]],
        },
        "hull_unflagged": hull_kept,
        "wall_s": round(wall, 1),
        "cpu_s": round(cpu, 1),
        "stage_s": {k: round(v, 1) for k, v in report["timings_s"].items()},
    }
    print(json.dumps(line))
    table.to_csv(root / "gt_imagery" / "crown_agreement.csv", index=False)


if __name__ == "__main__":
    main()
