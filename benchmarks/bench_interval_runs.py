"""How often the recommended volume's interval holds its measurand on whole runs of the demo's
orchards: simulated, mapped, segmented and measured as ``canopy-kit run --truth`` does.

    .venv/bin/python benchmarks/bench_interval_runs.py --orchard almond --seeds 8101 8102 ...
        [--rows 2] [--trees-per-row 6] [--preset adaptive] [--work DIR]

docs/VOLUMES.md gives the interval's coverage on single trees of every crown family; a run adds
what the segmentation does to a tree (touching almond crowns cut in the wrong place). Each seed
is simulated once into ``--work`` (kept, reused), run with the stage cache and scored against
its truth. Prints one JSON line per run (trees held / with a measurand, the missed trees'
IoU with their true tree) and the pooled coverage with its 95 % Clopper-Pearson interval,
over all trees, over the trees the segmentation got right (IoU >= 0.9) and per class of
``crown_contact`` (the share of a crown touching another tree's, ``segment.contact``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

GOOD_IOU = 0.9  # a tree segmented right: its points are (nearly) its true tree's
CONTACT_CLASSES = ((0.0, 0.03), (0.03, 0.08), (0.08, 1.01))  # crown_contact classes shown


def run_seed(work: Path, orchard: str, seed: int, rows: int, per_row: int, preset: str) -> dict:
    """Simulate (once) and run one seed; its interval figures."""
    import pandas as pd

    from canopy_kit.config import load_preset
    from canopy_kit.io.session_layout import find_bag
    from canopy_kit.pipeline import run
    from canopy_kit.sim import load_sim_config, simulate_session

    sim = work / f"{orchard}_{rows}x{per_row}_s{seed}"
    if not (sim / "truth" / "trees.csv").exists():
        layout = {"orchard": {"rows": rows, "trees_per_row": per_row}, "drone": {"enabled": False}}
        simulate_session(sim, load_sim_config(orchard, {**layout, "seed": seed}), overwrite=True)
    out = work / f"{sim.name}_{preset}_run"
    result = run(load_preset(preset), find_bag(sim), out, truth=sim)
    held = result.metrics["evaluation"]["volumes"].get("recommended_interval") or {}
    trees = pd.read_csv(out / "trees.csv")
    inside = (trees["volume_low_m3"] <= trees["true_measurand_m3"]) & (
        trees["true_measurand_m3"] <= trees["volume_high_m3"]
    )
    known = trees["true_measurand_m3"].notna()
    good = known & (trees["truth_iou"] >= GOOD_IOU)
    contact = trees["crown_contact"] if "crown_contact" in trees else pd.Series(float("nan"))
    by_contact = {}
    for lo, hi in CONTACT_CLASSES:
        mine = known & (contact >= lo) & (contact < hi)
        by_contact[f"{lo:g}-{min(hi, 1):g}"] = [int((inside & mine).sum()), int(mine.sum())]
    return {
        "orchard": orchard,
        "seed": seed,
        "trees": int(len(trees)),
        "held": int(held.get("held", 0)),
        "n": int(held.get("n", 0)),
        "missed_iou": held.get("missed_iou", []),
        "held_good_iou": int((inside & good).sum()),
        "n_good_iou": int(good.sum()),
        "held_by_contact": by_contact,
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
    parser.add_argument("--work", type=Path, default=Path("work/bench_interval_runs"))
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    runs = []
    for seed in args.seeds:
        figures = run_seed(
            args.work, args.orchard, seed, args.rows, args.trees_per_row, args.preset
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
    for label, k, n in pooled:
        if n:
            lo, hi = clopper_pearson(k, n)
            print(
                f"{args.orchard}, {label}: {k}/{n} held ({100 * k / n:.1f} %, "
                f"95 % CI {100 * lo:.1f}-{100 * hi:.1f} %)"
            )


if __name__ == "__main__":
    main()
