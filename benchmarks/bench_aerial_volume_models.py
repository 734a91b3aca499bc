"""Aerial volume models against the simulator's exact crown volume, per crown form and orchard.

Small simulated drone flights (2 rows x 3 trees) of every crown form (``[orchard] crown_form``)
of the pistachio and almond presets, processed by ``ground_truth.process_flight`` seeded by the
true tree positions; the crown stage is then run again from the saved rasters with the current
code, and every aerial volume model is compared with the exact envelope volume of the true
crown it was matched to (within 1.5 m; crowns cut by the mosaic border left out).

Prints one JSON line per model x form x orchard: mean signed error (bias) and MAPE in %, and a
Markdown table at the end (quoted in docs/GROUND_TRUTH.md, "Aerial volume models").

``--only limit`` (no photogrammetry): the same mirrored envelope on the exact top surface and
the exact widest level of 20 simulated trees per form and orchard, i.e. the error of the
invisible lower half alone.

Usage: ``python benchmarks/bench_aerial_volume_models.py [--work DIR] [--orchard KIND]...
[--form FORM]... [--only process|measure|limit]``. Flights are rendered and processed once into
``--work`` (default ``work/bench_aerial_volume_models``, git-ignored) and reused.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[1]
FORMS = ("ellipsoid", "lobed", "vase", "hedged", "sparse")
SEEDS = dict(zip(FORMS, (461, 462, 463, 464, 465)))  # used nowhere else
ORCHARDS = ("pistachio", "almond")
ROWS, TREES = 2, 3
MODELS = {
    "sphere, widest extent": "sphere_volume_m3",
    "sphere, mean diameter": "sphere_volume_mean_m3",
    "ellipsoid": "ellipsoid_volume_m3",
    "CHM integral": "chm_volume_m3",
    "envelope (2.5-D)": "envelope_volume_m3",
}


def flight_root(work: Path, kind: str, form: str) -> Path:
    """The folder of one flight (rendered session and its processing)."""
    return work / f"{kind}_{form}_{ROWS}x{TREES}_s{SEEDS[form]}"


def render(work: Path, kind: str, form: str) -> Path:
    """A rendered drone-only session of one crown form (cached)."""
    from canopy_kit.sim import load_sim_config
    from canopy_kit.sim.drone import simulate_drone_session

    root = flight_root(work, kind, form)
    if not (root / "truth" / "drone_cameras.csv").exists():
        cfg = load_sim_config(
            kind,
            {
                "seed": SEEDS[form],
                "drone": {"enabled": True},
                "orchard": {"rows": ROWS, "trees_per_row": TREES, "crown_form": form},
            },
        )
        t0 = time.perf_counter()
        simulate_drone_session(root, cfg)
        print(
            json.dumps({"rendered": root.name, "wall_s": round(time.perf_counter() - t0, 1)}),
            flush=True,
        )
    return root


def process(work: Path, kind: str, form: str) -> Path:
    """SfM, surface, mosaic and crowns of one flight, seeded by the true positions (cached)."""
    from canopy_kit.core.geo import LocalFrame
    from ground_truth import process_flight

    root = render(work, kind, form)
    out = root / "gt"
    if not (out / "report.json").exists():
        frame_json = json.loads((root / "truth" / "frame.json").read_text())
        frame = LocalFrame.from_dict(frame_json["frame"])
        t0, c0 = time.perf_counter(), time.process_time()
        process_flight(root / "drone", out, frame=frame, seeds=root / "truth" / "trees.csv")
        print(
            json.dumps(
                {
                    "processed": root.name,
                    "wall_s": round(time.perf_counter() - t0, 1),
                    "cpu_s": round(time.process_time() - c0, 1),
                }
            ),
            flush=True,
        )
    return out


def measure(work: Path, kind: str, form: str) -> list[dict]:
    """Every model's bias and MAPE on one processed flight (crowns measured by the current code)."""
    from canopy_kit.evaluate.stats import agreement
    from ground_truth.match import assign

    root = flight_root(work, kind, form)
    truth = pd.read_csv(root / "truth" / "trees.csv")
    _, _, crowns = recrown(root / "gt", root / "truth" / "trees.csv")
    c = crowns[~crowns["touches_border"].astype(bool)].reset_index(drop=True)
    ia, ib, _ = assign(truth[["crown_x", "crown_y"]].to_numpy(), c[["x", "y"]].to_numpy(), 1.5)
    true_v = truth["crown_volume_m3"].to_numpy(float)[ia]
    lines = []
    for model, col in MODELS.items():
        line = {
            "orchard": kind,
            "form": form,
            "model": model,
            "crowns": len(ia),
            "trees": len(truth),
            "bias_pct": np.nan,
            "mape_pct": np.nan,
        }
        if len(ia) >= 2:  # else no crowns found (sparse crowns): a row that says so
            a = agreement(c[col].to_numpy(float)[ib], true_v)
            line.update(bias_pct=round(a.bias_pct, 1), mape_pct=round(a.mape_pct, 1))
        lines.append(line)
    return lines


def recrown(gt_dir: Path, seeds: Path | None) -> tuple[object, object, pd.DataFrame]:
    """A processed flight read back from disk with its crown stage run again by the current code."""
    from ground_truth.crowns import delineate_crowns, measure_crowns
    from ground_truth.match import read_trees
    from ground_truth.pipeline import load_result
    from ground_truth.raster import sample_bilinear

    result = load_result(gt_dir)
    ox, oy = result.ortho.grid.centers()
    chm = sample_bilinear(result.surface.grid, result.surface.chm, ox, oy)
    xy = read_trees(seeds, result.frame)[["tree_x", "tree_y"]].to_numpy() if seeds else None
    seg = delineate_crowns(result.ortho.rgb, result.ortho.valid, chm, result.ortho.grid, xy)
    return result, seg, measure_crowns(seg, chm)


def mirror_limit(
    kind: str, form: str, rows: int = 4, trees: int = 5, seed: int = 466, cell_m: float = 0.05
) -> dict:
    """The mirrored 2.5-D envelope with perfect imagery: the exact top surface of each crown
    above its exact widest level, mirrored below (no photogrammetry), against the exact volume.

    The widest level is the height of the crown's largest horizontal cross-section.
    """
    from canopy_kit.sim import load_sim_config
    from canopy_kit.sim.orchard import generate_orchard

    cfg = load_sim_config(
        kind, {"orchard": {"rows": rows, "trees_per_row": trees, "crown_form": form}}
    )
    orchard = generate_orchard(cfg.orchard, np.random.default_rng(seed))
    ratios, upper = [], []
    for tree in orchard.trees:
        env = tree.crown
        lo, hi = env.bounds
        xs = np.arange(lo[0], hi[0], cell_m) + cell_m / 2
        ys = np.arange(lo[1], hi[1], cell_m) + cell_m / 2
        zs = np.linspace(*env.z_range, 81)
        gx, gy = (a.ravel() for a in np.meshgrid(xs, ys))
        pts = np.column_stack(
            [np.repeat(gx, len(zs)), np.repeat(gy, len(zs)), np.tile(zs, len(gx))]
        )
        inside = env.contains(pts).reshape(len(gx), len(zs))
        has = inside.any(axis=1)
        top = zs[len(zs) - 1 - np.argmax(inside[:, ::-1], axis=1)][has]
        widest = zs[np.argmax(inside.sum(axis=0))]
        column = np.clip(np.minimum(2 * (top - widest), top - tree.base[2]), 0.0, None)
        ratios.append(column.sum() * cell_m**2 / env.volume)
        upper.append(np.clip(top - widest, 0.0, None).sum() * cell_m**2 / env.volume)
    r = np.array(ratios)
    return {
        "orchard": kind,
        "form": form,
        "trees": len(r),
        "mirror_bias_pct": round(100 * (r.mean() - 1), 1),
        "mirror_p5_p95": [round(float(q), 3) for q in np.percentile(r, [5, 95])],
        "upper_share_of_volume": round(float(np.mean(upper)), 3),
    }


def table(lines: list[dict]) -> str:
    """Markdown: one row per orchard x form, one column per model, "bias (MAPE)"."""
    df = pd.DataFrame(lines)
    head = "| orchard | form | crowns | " + " | ".join(MODELS) + " |"
    out = [head, "|" + "---|" * (3 + len(MODELS))]
    for (kind, form), g in df.groupby(["orchard", "form"], sort=False):
        by = g.set_index("model")
        cells = [
            f"{by.loc[m, 'bias_pct']:+.1f} % ({by.loc[m, 'mape_pct']:.1f})"
            if m in by.index and np.isfinite(by.loc[m, "bias_pct"])
            else "-"
            for m in MODELS
        ]
        out.append(
            f"| {kind} | {form} | {int(g['crowns'].iloc[0])} / {int(g['trees'].iloc[0])} | "
            + " | ".join(cells)
            + " |"
        )
    for kind, g in df.groupby("orchard", sort=False):
        cells = []
        for m in MODELS:
            s = g[(g["model"] == m) & np.isfinite(g["bias_pct"])]
            bias = np.average(s["bias_pct"], weights=s["crowns"]) if len(s) else np.nan
            mape = np.average(s["mape_pct"], weights=s["crowns"]) if len(s) else np.nan
            cells.append(f"{bias:+.1f} % ({mape:.1f})" if len(s) else "-")
        out.append(
            f"| {kind} | all forms | {int(g.groupby('form')['crowns'].first().sum())} | "
            + " | ".join(cells)
            + " |"
        )
    return "\n".join(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=REPO / "work" / "bench_aerial_volume_models")
    parser.add_argument("--orchard", action="append", choices=ORCHARDS)
    parser.add_argument("--form", action="append", choices=FORMS)
    parser.add_argument("--only", choices=["process", "measure", "limit"])
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    flights = [(k, f) for f in (args.form or FORMS) for k in (args.orchard or ORCHARDS)]
    if args.only in (None, "process"):
        for kind, form in flights:
            process(args.work, kind, form)
    if args.only in (None, "measure"):
        lines = []
        for kind, form in flights:
            if (flight_root(args.work, kind, form) / "gt" / "report.json").exists():
                for line in measure(args.work, kind, form):
                    print(json.dumps(line), flush=True)
                    lines.append(line)
        if lines:
            print(table(lines))
    if args.only in (None, "limit"):
        for kind, form in flights:
            print(json.dumps(mirror_limit(kind, form)), flush=True)


if __name__ == "__main__":
    main()
