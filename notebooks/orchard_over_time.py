import marimo

__generated_with = "0.25.2"
app = marimo.App(width="medium")


@app.cell
def _():
    import marimo as mo
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from canopy_kit.store import (
        OrchardStore,
        changes,
        growth,
        orchard_trees,
        row_growth,
        stored_methods,
    )
    from canopy_kit.store import sessions as stored_sessions

    return (OrchardStore, changes, growth, mo, np, orchard_trees, plt, row_growth, stored_methods,
            stored_sessions)


@app.cell
def _(mo):
    mo.md(
        """
        # An orchard over time

        Every session of an orchard store (`canopy-kit batch ... --out OUT` writes
        `OUT/orchard.duckdb`): growth per tree and per row, and a map coloured by change.
        Run with `-- --store OUT/orchard.duckdb`; without it, a small synthetic store is
        made (three visits of 4 rows of 8 trees, GNSS offsets, growth, one tree removed and
        replanted) so the notebook shows its views.
        """
    )
    return


@app.cell
def _(OrchardStore, mo, np, stored_sessions):
    import datetime as dt
    import tempfile
    from pathlib import Path

    import pandas as pd

    def demo_store() -> Path:
        """Three visits of a synthetic planting through OrchardStore.ingest."""
        from canopy_kit import ALPHA_COLUMN, LocalFrame
        from canopy_kit.store import SessionRecord

        rng = np.random.default_rng(0)
        layout = np.array([[r * 6.0, i * 5.0] for r in range(4) for i in range(8)])
        base = rng.uniform(15, 35, len(layout))
        frame = LocalFrame.at(37.281, -120.42)
        path = Path(tempfile.mkdtemp()) / "orchard.duckdb"
        visits = [("spring", 4, 1.0, ()), ("summer", 6, 1.35, (10,)), ("autumn", 9, 1.7, ())]
        with OrchardStore(path) as db:
            for sid, month, grow, absent in visits:
                xy = layout + rng.normal(0, 1.0, 2) + rng.normal(0, 0.1, layout.shape)
                vol = base * grow * rng.normal(1, 0.04, len(layout)) * (1 + 0.15 * (layout[:, 0] > 10))
                if sid == "autumn":
                    vol[10] = 3.0  # replanted
                lat, lon, _ = frame.to_wgs84(np.column_stack([xy, np.zeros(len(xy))]))
                keep = np.setdiff1d(np.arange(len(layout)), absent)
                t = pd.DataFrame({"segment": np.arange(len(xy)), "label": "", "row": layout[:, 0] // 6,
                                  "lat": lat, "lon": lon, "n_points": 5000, "height_m": 4.0,
                                  "crown_diameter_m": 4.0, ALPHA_COLUMN: vol,
                                  # the interval a run gives its recommended estimator
                                  "volume_method": "alpha_shape", "volume_low_m3": 0.9 * vol,
                                  "volume_high_m3": 1.15 * vol}).iloc[keep]
                db.ingest(SessionRecord(sid, "demo", dt.date(2025, month, 1)), t)
        return path

    given = mo.cli_args().get("store")
    store_path = Path(given) if given else demo_store()
    db = OrchardStore(store_path, read_only=True)
    sessions = stored_sessions(db)
    mo.vstack([mo.md(f"Store: `{store_path}`{' (synthetic demo)' if not given else ''}"), sessions])
    return db, sessions


@app.cell
def _(db, mo, sessions, stored_methods):
    orchards = sorted(sessions["orchard"].unique())
    orchard = mo.ui.dropdown(orchards, value=orchards[0], label="Orchard")
    methods = stored_methods(db)
    method = mo.ui.dropdown(methods, value=db.volume_method if db.volume_method in methods else None,
                            label="Volume method")
    mo.hstack([orchard, method])
    return method, orchard


@app.cell
def _(db, growth, method, orchard, plt, row_growth):
    g = growth(db, method=method.value, orchard=orchard.value)
    rows = row_growth(db, method=method.value, orchard=orchard.value)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4))
    for _, tree in g.groupby("tree_id"):
        a1.plot(tree["date"], tree["volume_m3"], "-o", ms=3, lw=0.8, alpha=0.6)
    a1.set(title="Volume per tree", ylabel="volume (m³)")
    for r, part in rows.groupby("tree_row"):
        a2.plot(part["date"], part["mean_volume_m3"], "-o", label=f"row {r}")
    a2.set(title="Mean volume per row", ylabel="volume (m³)")
    a2.legend(fontsize=8)
    fig.autofmt_xdate()
    fig
    return (g,)


@app.cell
def _(changes, db, g, mo, np, orchard, orchard_trees, plt):
    last = g[g["date"] == g["date"].max()]
    trees = orchard_trees(db, orchard.value)
    fig2, ax = plt.subplots(figsize=(7, 6))
    sc = ax.scatter(last["x"], last["y"], c=100 * last["growth_since_first"], cmap="viridis", s=80)
    fig2.colorbar(sc, ax=ax, label="growth since first visit (%)")
    for status, marker in (("missing", "x"), ("removed", "s")):
        t = trees[trees["status"] == status]
        style = {"color": "red"} if marker == "x" else {"facecolors": "none", "edgecolors": "red"}
        ax.scatter(t["x"], t["y"], marker=marker, s=120, label=status, **style)
    grew = last[last["change_since_first"] == "grew"]  # intervals apart: measurably grown
    ax.scatter(grew["x"], grew["y"], s=220, facecolors="none", edgecolors="black", lw=1.2,
               label="grew beyond the intervals")
    young = last[last["kind"] == "replanted"]
    ax.scatter(young["x"], young["y"], marker="*", color="orange", s=160, label="replanted")
    ax.set(title=f"Change by the last visit ({g['date'].max()})", xlabel="x (m)", ylabel="y (m)",
           aspect="equal")
    ax.legend(fontsize=8, loc="upper right")
    ev = changes(db, orchard.value)
    summary = (f"{len(trees)} trees known, median growth since first visit "
               f"{100 * np.nanmedian(last['growth_since_first']):.0f} %")
    told = last["change_since_first"].dropna()
    if len(told):  # the method carries the runs' intervals
        counts = told.value_counts()
        summary += (f"; by their volume intervals {counts.get('grew', 0)} of {len(told)} trees "
                    f"grew measurably, {counts.get('shrank', 0)} shrank, "
                    f"{counts.get('within the intervals', 0)} changed within the intervals")
    mo.vstack([fig2, mo.md(summary), ev])
    return


if __name__ == "__main__":
    app.run()
