"""How often the recommended volume's interval holds its measurand on whole runs of the demo's
orchards: simulated, mapped, segmented and measured as ``canopy-kit run --truth`` does.

    .venv/bin/python benchmarks/bench_interval_runs.py --orchard almond --seeds 8101 8102 ...
        [--rows 2] [--trees-per-row 6] [--preset adaptive] [--sensor vlp16] [--work DIR]

docs/VOLUMES.md gives the interval's coverage on single trees of every crown family; a run adds
what the segmentation does to a tree (touching almond crowns cut in the wrong place). Each seed
is simulated once into ``--work`` (kept, reused), run with the stage cache and scored against
its truth. Prints one JSON line per run (trees held / with a measurand, the missed trees'
IoU with their true tree) and the pooled coverage with its 95 % Clopper-Pearson interval,
over all trees, over the trees the segmentation got right (IoU >= 0.9) and per class of
``crown_contact`` (the share of a crown touching another tree's, ``segment.contact``).

Per class it also gives how many trees the families' interval alone would have held (the
volume stage's interval, read from the run's stage cache before ``volume.interwoven`` widens
it), and the truth / estimate ratios of the interwoven trees (``crown_contact`` at or above
``TOUCHING_CONTACT``), which set that widening. ``--sensor`` simulates another LiDAR model
(``canopy_kit.sim.config.SENSOR_MODELS``; default: the orchard preset's own).
"""

from __future__ import annotations

import argparse
import json
import pickle
from pathlib import Path

import numpy as np
import pandas as pd

GOOD_IOU = 0.9  # a tree segmented right: its points are (nearly) its true tree's
CONTACT_CLASSES = ((0.0, 0.03), (0.03, 0.08), (0.08, 1.01))  # crown_contact classes shown


def unwidened_interval(out: Path) -> pd.DataFrame | None:
    """Per segment: the volume stage's interval (``volume_low_m3``, ``volume_high_m3``), as
    the tree families' calibration set it before the table widened interwoven crowns; read
    from the run's stage cache (the newest entry: the run just made it, older ones are other
    code's), None without one."""
    entries = sorted((out / ".cache").glob("volumes-*.pkl"), key=lambda e: e.stat().st_mtime)
    if not entries:
        return None
    with entries[-1].open("rb") as fh:
        volumes = pickle.load(fh)
    return volumes.table.set_index("segment")[["volume_low_m3", "volume_high_m3"]]


def run_seed(
    work: Path,
    orchard: str,
    seed: int,
    rows: int,
    per_row: int,
    preset: str,
    sensor: str | None = None,
) -> dict:
    """Simulate (once) and run one seed; its interval figures."""
    from canopy_kit.config import load_preset
    from canopy_kit.io.session_layout import find_bag
    from canopy_kit.pipeline import run
    from canopy_kit.sim import load_sim_config, simulate_session

    name = orchard if sensor is None else f"{orchard}_{sensor}"
    sim = work / f"{name}_{rows}x{per_row}_s{seed}"
    if not (sim / "truth" / "trees.csv").exists():
        layout = {"orchard": {"rows": rows, "trees_per_row": per_row}, "drone": {"enabled": False}}
        config = load_sim_config(orchard, {**layout, "seed": seed}, sensor=sensor)
        simulate_session(sim, config, overwrite=True)
    out = work / f"{sim.name}_{preset}_run"
    pipeline = load_preset(preset)
    result = run(pipeline, find_bag(sim), out, truth=sim)
    held = result.metrics["evaluation"]["volumes"].get("recommended_interval") or {}
    trees = pd.read_csv(out / "trees.csv")
    return {
        "orchard": orchard,
        "sensor": sensor,
        "seed": seed,
        "trees": int(len(trees)),
        "held": int(held.get("held", 0)),
        "n": int(held.get("n", 0)),
        "missed_iou": held.get("missed_iou", []),
        **score_trees(trees, unwidened_interval(out), pipeline.volume.recommended),
    }


def score_trees(trees: pd.DataFrame, raw: pd.DataFrame | None, recommended: str) -> dict:
    """A run's interval figures from its tree table (``trees.csv`` with truth) and the
    unwidened interval per segment (:func:`unwidened_interval`; None: not scored)."""
    from canopy_kit.segment.contact import TOUCHING_CONTACT
    from canopy_kit.volume.verb import volume_column

    truth = trees["true_measurand_m3"]
    inside = (trees["volume_low_m3"] <= truth) & (truth <= trees["volume_high_m3"])
    known = truth.notna()
    good = known & (trees["truth_iou"] >= GOOD_IOU)
    nan = pd.Series(np.nan, index=trees.index)
    contact = trees["crown_contact"] if "crown_contact" in trees else nan
    inside_raw = pd.Series(False, index=trees.index)
    if raw is not None:
        segment = trees["segment"]
        low, high = segment.map(raw["volume_low_m3"]), segment.map(raw["volume_high_m3"])
        inside_raw = (low <= truth) & (truth <= high)
    by_contact, unwidened = {}, {}
    for lo, hi in CONTACT_CLASSES:
        mine = known & (contact >= lo) & (contact < hi)
        by_contact[f"{lo:g}-{min(hi, 1):g}"] = [int((inside & mine).sum()), int(mine.sum())]
        unwidened[f"{lo:g}-{min(hi, 1):g}"] = [int((inside_raw & mine).sum()), int(mine.sum())]
    woven = known & (contact >= TOUCHING_CONTACT)
    ratios = (truth / trees[volume_column(recommended)])[woven]
    return {
        "held_good_iou": int((inside & good).sum()),
        "n_good_iou": int(good.sum()),
        "held_by_contact": by_contact,
        "held_unwidened_by_contact": unwidened if raw is not None else None,
        "interwoven_ratios": [round(float(r), 3) for r in ratios],
    }


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Exact binomial confidence interval of a share ``k / n``."""
    from scipy.stats import beta

    a = (1 - level) / 2
    lo = 0.0 if k == 0 else float(beta.ppf(a, k, n - k + 1))
    hi = 1.0 if k == n else float(beta.ppf(1 - a, k + 1, n - k))
    return lo, hi


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--orchard", default="almond")
    parser.add_argument("--seeds", type=int, nargs="+", required=True)
    parser.add_argument("--rows", type=int, default=2)
    parser.add_argument("--trees-per-row", type=int, default=6)
    parser.add_argument("--preset", default="adaptive")
    parser.add_argument(
        "--sensor", default=None, help="LiDAR model (SENSOR_MODELS); default: the orchard's own"
    )
    parser.add_argument("--work", type=Path, default=Path("work/bench_interval_runs"))
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    runs = []
    for seed in args.seeds:
        figures = run_seed(
            args.work, args.orchard, seed, args.rows, args.trees_per_row, args.preset, args.sensor
        )
        print(json.dumps(figures), flush=True)
        runs.append(figures)
    classes = [f"{lo:g}-{min(hi, 1):g}" for lo, hi in CONTACT_CLASSES]
    pooled = [
        ("every tree", sum(r["held"] for r in runs), sum(r["n"] for r in runs)),
        (
            f"trees segmented right (IoU >= {GOOD_IOU})",
            sum(r["held_good_iou"] for r in runs),
            sum(r["n_good_iou"] for r in runs),
        ),
    ] + [
        (
            f"crown_contact {c}",
            sum(r["held_by_contact"][c][0] for r in runs),
            sum(r["held_by_contact"][c][1] for r in runs),
        )
        for c in classes
    ]
    if all(r["held_unwidened_by_contact"] is not None for r in runs):
        pooled += [
            (
                f"crown_contact {c}, the families' interval alone (unwidened)",
                sum(r["held_unwidened_by_contact"][c][0] for r in runs),
                sum(r["held_unwidened_by_contact"][c][1] for r in runs),
            )
            for c in classes
        ]
    what = args.orchard if args.sensor is None else f"{args.orchard} ({args.sensor})"
    for label, k, n in pooled:
        if n:
            lo, hi = clopper_pearson(k, n)
            print(
                f"{what}, {label}: {k}/{n} held ({100 * k / n:.1f} %, "
                f"95 % CI {100 * lo:.1f}-{100 * hi:.1f} %)"
            )
    ratios = np.array([r for run in runs for r in run["interwoven_ratios"]], dtype=float)
    ratios = ratios[np.isfinite(ratios)]
    if len(ratios):
        q = np.quantile(ratios, [0.0, 0.02, 0.5, 0.98, 1.0])
        print(
            f"{what}, truth / estimate of {len(ratios)} interwoven trees: min {q[0]:.3f}, "
            f"2 % {q[1]:.3f}, median {q[2]:.3f}, 98 % {q[3]:.3f}, max {q[4]:.3f}"
        )


if __name__ == "__main__":
    main()
