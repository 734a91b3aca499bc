"""Issue 52's table from the saved per-session results: orchard x sensor x method.

    python benchmarks/issue52_table.py --seeds 701 702 703

Reads ``canopy_kit/paper/data/segmentation_results.csv`` (written by ``bench_segment.py
accuracy --csv``) and prints, per orchard, sensor and method: sessions, true trees, segments,
trees one to one (point IoU >= 0.5), success (one-to-one / true trees, pooled), precision
(one-to-one / segments, pooled), the per-session minimum of both and, on the crown orchards,
the trees the exact crown envelopes separate (the ceiling; on a wall the truth is the
trunk-midpoint cut, which no envelope gives, so none is shown). The hedgerow sessions
are ``almond`` with ``orchard.crown_form=hedged`` (variant ``hedged`` or ``hedged_<sensor>``).
"""

from __future__ import annotations

import argparse

import pandas as pd

ORCHARDS = ["pistachio", "almond", "almond-paper", "hedgerow", "fruiting-wall"]
METHODS = ["dbscan", "dbscan_spectral", "adaptive", "wall"]


def per_session(csv: str, seeds: list[int]) -> pd.DataFrame:
    d = pd.read_csv(csv)
    d = d[d["seed"].isin(seeds)].copy()
    v = d["variant"].astype(str)
    hedged = v.str.startswith("hedged")
    d["orchard"] = d["orchard"].where(~hedged, "hedgerow")
    sensor = v.str.replace(r"^hedged_?", "", regex=True).replace({"": "default"})
    d["sensor"] = sensor.where(sensor != "default", "32-ring (default)")
    d["correct"] = (d["success_points"] * d["n_truth"]).round().astype(int)
    d["success"] = d["correct"] / d["n_truth"]
    d["precision"] = d["correct"] / d["n_predicted"].where(d["n_predicted"] > 0)
    d["ceiling"] = (d["ceiling_points"] * d["n_truth"]).round().astype(int)
    return d.fillna({"precision": 0.0})


def table(d: pd.DataFrame) -> pd.DataFrame:
    g = d.groupby(["orchard", "sensor", "method"])
    t = g.agg(
        sessions=("seed", "nunique"),
        trees=("n_truth", "sum"),
        segments=("n_predicted", "sum"),
        correct=("correct", "sum"),
        min_success=("success", "min"),
        min_precision=("precision", "min"),
        ceiling=("ceiling", "sum"),
    ).reset_index()
    t["success"] = t["correct"] / t["trees"]
    t["precision"] = t["correct"] / t["segments"]
    order = {o: i for i, o in enumerate(ORCHARDS)}
    morder = {m: i for i, m in enumerate(METHODS)}
    t["_o"], t["_m"] = t["orchard"].map(order), t["method"].map(morder)
    sensors = ["32-ring (default)", "vlp16", "hdl32", "os0-32", "os1-64", "os1-128", "livox-mid360"]
    t["_s"] = t["sensor"].map({s: i for i, s in enumerate(sensors)}).fillna(len(sensors))
    return t.sort_values(["_o", "_s", "sensor", "_m"]).drop(columns=["_o", "_m", "_s"])


def compact(t: pd.DataFrame) -> None:
    """One line per orchard and sensor: success / precision pooled, the worst session's in
    brackets, for each method."""

    def cell(r) -> str:
        if r is None:
            return ""
        return (
            f"{100 * r.success:.1f} / {100 * r.precision:.1f} "
            f"({100 * r.min_success:.0f} / {100 * r.min_precision:.0f})"
        )

    print(
        "| orchard | sensor | sessions | trees | dbscan | dbscan_spectral | **adaptive** "
        "| **wall** | ceiling |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for (orchard, sensor), g in t.groupby(["orchard", "sensor"], sort=False):
        by = {r.method: r for r in g.itertuples()}
        a = by.get("adaptive")
        rec = "wall" if orchard == "fruiting-wall" else "adaptive"
        cells = {m: cell(by.get(m)) for m in METHODS}
        cells[rec] = f"**{cells[rec]}**"
        print(
            f"| {orchard} | {sensor} | {a.sessions} | {a.trees} | {cells['dbscan']} | "
            f"{cells['dbscan_spectral']} | {cells['adaptive']} | {cells['wall']} | "
            f"{a.ceiling if orchard != 'fruiting-wall' else ''} |"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--csv", default="canopy_kit/paper/data/segmentation_results.csv")
    ap.add_argument("--seeds", nargs="+", type=int, default=[701, 702, 703])
    ap.add_argument("--sessions", action="store_true", help="also list every session")
    ap.add_argument("--long", action="store_true", help="one line per method (else per orchard)")
    args = ap.parse_args()
    d = per_session(args.csv, args.seeds)
    t = table(d)
    if not args.long:
        compact(t)
        if args.sessions:
            sessions(d)
        return

    def pct(v: float) -> str:
        return f"{100 * v:.1f} %"

    print(
        "| orchard | sensor | method | sessions | trees | segments | one-to-one | success "
        "| min per session | precision | min per session | ceiling |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in t.itertuples():
        bold = r.method in ("adaptive", "wall")
        s, p = pct(r.success), pct(r.precision)
        print(
            f"| {r.orchard} | {r.sensor} | {r.method} | {r.sessions} | {r.trees} | {r.segments} | "
            f"{r.correct} | {'**' + s + '**' if bold else s} | {pct(r.min_success)} | "
            f"{'**' + p + '**' if bold else p} | {pct(r.min_precision)} | "
            f"{r.ceiling if r.method == 'adaptive' and r.orchard != 'fruiting-wall' else ''} |"
        )
    if args.sessions:
        sessions(d)


def sessions(d: pd.DataFrame) -> None:
    cols = ["session", "method", "n_truth", "n_predicted", "correct", "n_merged", "n_split"]
    print(d[cols + ["n_other"]].to_string(index=False))


if __name__ == "__main__":
    main()
