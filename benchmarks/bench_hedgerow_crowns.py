"""Touching crowns from the imagery alone: crowns one-to-one and row extents on 4 × 8 flights.

Prints the numbers of docs/GROUND_TRUTH.md ("Touching crowns from the imagery alone"). Each
flight is rendered and processed once (photos → SfM, surface, orthomosaic, crowns: the
timed part), cached in ``--work``; then the crown stage is run again from the processed
rasters with each way of seeding the crowns:

* ``rows``: the default without seed trees (``ground_truth.row_seeds``), spacing from the
  crowns' width across the row;
* ``rows, spacing given``: the same with the planting distance given (``tree_spacing_m``,
  the preset's mean spacing 4.75 m for almond, 5 m for pistachio);
* ``chm_maxima``: one crown per CHM maximum (the imagery-only mode before);
* ``tree_positions``: seeded by the true trunk positions (what LiDAR seeds give at best).

Against the simulator's truth: trees with a crown of their own within 1.5 m (Hungarian,
mosaic-border crowns left out), extra crowns, and the crowns' extents along and across the
row against the crown envelopes projected on the orchard's row direction.

``TUNING`` flights were looked at while the method was designed; ``HELD_OUT`` flights were
not, and are the ones quoted as results.

Usage: ``python benchmarks/bench_hedgerow_crowns.py [--work DIR] [--set tuning|held_out|all]
[--markdown]``.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import pandas as pd

REPO = Path(__file__).resolve().parents[1]
# (name, preset, seed, orchard overrides)
TUNING = [
    ("almond_4x8_s21", "almond", 21, {}),
    ("almond_4x8_s22", "almond", 22, {}),
    ("almond_4x8_s23", "almond", 23, {}),
    (
        "almond_mix_s24",
        "almond",
        24,
        {"row_bearing_deg": 35, "row_bow": 1.0, "crown_form": "mix"},
    ),
    ("pistachio_4x8_s21", "pistachio", 21, {}),
    ("almond_2x5_s57", "almond", 57, {"rows": 2, "trees_per_row": 5}),
]
HELD_OUT = [
    ("almond_4x8_s31", "almond", 31, {}),
    ("almond_4x8_s32", "almond", 32, {}),
    ("almond_4x8_s41", "almond", 41, {}),
    ("almond_4x8_s42", "almond", 42, {}),
    ("almond_4x8_s43", "almond", 43, {}),
    (
        "almond_lobed_s33",
        "almond",
        33,
        {"row_bearing_deg": 120, "row_bow": 1.5, "crown_form": "lobed"},
    ),
    (
        "almond_vase_s44",
        "almond",
        44,
        {"row_bearing_deg": 60, "row_bow": 1.0, "crown_form": "vase"},
    ),
    ("almond_hedged_s45", "almond", 45, {"row_bearing_deg": 150, "crown_form": "hedged"}),
    ("pistachio_4x8_s31", "pistachio", 31, {}),
    ("pistachio_4x8_s41", "pistachio", 41, {}),
]
PLANTING_DISTANCE_M = {"almond": 4.75, "pistachio": 5.0}


def processed_flight(work: Path, name: str, preset: str, seed: int, orchard: dict) -> dict:
    """Render (cached) and process (cached) one flight; the processing's wall and CPU time."""
    from canopy_kit.core.geo import LocalFrame
    from canopy_kit.sim import load_sim_config
    from canopy_kit.sim.drone import simulate_drone_session
    from ground_truth import process_flight

    root = work / name
    if not (root / "truth" / "drone_cameras.csv").exists():
        overrides = {"rows": 4, "trees_per_row": 8, **orchard}
        cfg = load_sim_config(
            preset, {"seed": seed, "orchard": overrides, "drone": {"enabled": True}}
        )
        simulate_drone_session(root, cfg)
    timing = root / "gt_timing.json"
    if not timing.exists():
        frame = LocalFrame.from_dict(
            json.loads((root / "truth" / "frame.json").read_text())["frame"]
        )
        t0, c0 = time.perf_counter(), time.process_time()
        result = process_flight(root / "drone", root / "gt", frame=frame)
        spent = {
            "photos": result.report["sfm"]["total_images"],
            "wall_s": round(time.perf_counter() - t0, 1),
            "cpu_s": round(time.process_time() - c0, 1),
            "load_average": round(os.getloadavg()[0], 2),
            "stages_s": {k: round(v, 1) for k, v in result.report["timings_s"].items()},
        }
        timing.write_text(json.dumps(spent))
    return json.loads(timing.read_text())


def score(work: Path, name: str, preset: str) -> list[dict]:
    """Each seeding's crowns against the truth, from the processed rasters."""
    from canopy_kit.sim.truth import crown_row_extents
    from ground_truth.crowns import CrownOptions, delineate_crowns, measure_crowns
    from ground_truth.flight_accuracy import crown_agreement
    from ground_truth.match import read_trees
    from ground_truth.pipeline import load_result
    from ground_truth.raster import sample_bilinear

    root = work / name
    result = load_result(root / "gt")
    ox, oy = result.ortho.grid.centers()
    chm = sample_bilinear(result.surface.grid, result.surface.chm, ox, oy)
    truth = pd.read_csv(root / "truth" / "trees.csv").merge(crown_row_extents(root), on="tree_id")
    trunks = read_trees(root / "truth" / "trees.csv", result.frame)[["tree_x", "tree_y"]]
    seedings = {
        "rows": (None, CrownOptions()),
        "rows, spacing given": (
            None,
            CrownOptions(tree_spacing_m=PLANTING_DISTANCE_M[preset]),
        ),
        "chm_maxima": (None, CrownOptions(unseeded="chm_maxima")),
        "tree_positions": (trunks.to_numpy(), CrownOptions()),
    }
    lines = []
    for seeding, (seeds, options) in seedings.items():
        t0 = time.perf_counter()
        seg = delineate_crowns(
            result.ortho.rgb, result.ortho.valid, chm, result.ortho.grid, seeds, options
        )
        crowns = measure_crowns(seg, chm)
        seconds = time.perf_counter() - t0
        _, m = crown_agreement(crowns, truth)
        lines.append(
            {
                "flight": name,
                "seeding": seeding,
                "trees": m["trees"],
                "one_to_one": m["matched"],
                "extra_crowns": m["unmatched_crowns"],
                "across_row_mae_m": round(m["across_row_mae_m"], 3),
                "across_row_bias_m": round(m["across_row_bias_m"], 3),
                "along_row_mae_m": round(m["along_row_mae_m"], 3),
                "along_row_mae_free_m": round(m["along_row_mae_free_m"], 3),
                "free_standing": m["free_standing"],
                "row_layout": seg.row_layout.to_dict() if seg.row_layout else None,
                "crown_stage_s": round(seconds, 1),
            }
        )
    return lines


def markdown(lines: list[dict]) -> str:
    """One row per flight and seeding: one-to-one / trees (+ extra), across and along MAE."""
    out = [
        "| flight | seeding | one-to-one | extra | across-row MAE (bias) | along-row MAE |",
        "|---|---|---|---|---|---|",
    ]
    for x in lines:
        out.append(
            f"| {x['flight']} | {x['seeding']} | {x['one_to_one']} / {x['trees']} | "
            f"{x['extra_crowns']} | {x['across_row_mae_m']:.2f} ({x['across_row_bias_m']:+.2f}) m "
            f"| {x['along_row_mae_m']:.2f} m |"
        )
    totals = (
        pd.DataFrame(lines)
        .groupby("seeding", sort=False)[["one_to_one", "trees", "extra_crowns"]]
        .sum()
    )
    out.append("")
    out.append("| seeding | one-to-one, all flights | extra crowns |")
    out.append("|---|---|---|")
    for seeding, t in totals.iterrows():
        out.append(
            f"| {seeding} | {t.one_to_one} / {t.trees} ({t.one_to_one / t.trees:.1%}) | "
            f"{t.extra_crowns} |"
        )
    return "\n".join(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=REPO / "work" / "bench_hedgerow_crowns")
    parser.add_argument("--set", choices=("tuning", "held_out", "all"), default="held_out")
    parser.add_argument("--markdown", action="store_true", help="also print markdown tables")
    args = parser.parse_args()
    flights = {"tuning": TUNING, "held_out": HELD_OUT, "all": TUNING + HELD_OUT}[args.set]
    args.work.mkdir(parents=True, exist_ok=True)
    print(json.dumps({"cpu_count": os.cpu_count(), "load_average": os.getloadavg()}))
    lines = []
    for name, preset, seed, orchard in flights:
        spent = processed_flight(args.work, name, preset, seed, orchard)
        print(json.dumps({"flight": name, "photos_to_crowns": spent}), flush=True)
        for line in score(args.work, name, preset):
            print(json.dumps(line), flush=True)
            lines.append(line)
    if args.markdown:
        print(markdown(lines))


if __name__ == "__main__":
    main()
