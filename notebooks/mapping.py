import marimo

__generated_with = "0.25.2"
app = marimo.App(width="medium")


@app.cell
def _():
    import marimo as mo
    import matplotlib

    matplotlib.use("Agg")
    import pandas as pd

    from canopy_kit import load_context, load_truth
    from canopy_kit.mapping.plots import mapping_figures

    return load_context, load_truth, mapping_figures, mo, pd


@app.cell
def _(load_context, mo):
    args = mo.cli_args()
    session = str(args.get("session", "out/demo/pistachio_session"))
    ctx = load_context(session, run_dir=args.get("run"), use_drone=False)
    mo.md(f"# Mapping\n\nSession `{session}`")
    return ctx, session


@app.cell
def _(ctx, mo, pd):
    d = ctx.mapping.diagnostics
    ev = ctx.evaluation.get("mapping", {})
    rows = [
        ("path length (m)", d.get("path_length_m")),
        ("scans registered", d.get("sweeps_registered")),
        ("real-time factor (CPU)", d.get("real_time_factor_cpu")),
        ("georeferenced", d.get("georeferenced")),
        ("ATE RMSE (m)", ev.get("ate_rmse_m")),
        ("drift (% of path)", ev.get("drift_percent")),
        ("rotation RMSE (deg)", ev.get("rotation_rmse_deg")),
        ("map to true surfaces, median (m)", ev.get("map_aligned", {}).get("median_m")),
    ]
    mo.vstack([mo.ui.table(pd.DataFrame(rows, columns=["quantity", "value"]), selection=None),
               mo.md("\n".join(f"- warning: {w}" for w in ctx.mapping.warnings))])
    return (ev,)


@app.cell
def _(ctx, ev, load_truth, mapping_figures):
    reference = load_truth(ctx.truth_dir).trajectory if ctx.truth_dir is not None else None
    figs = mapping_figures(ctx.mapping, reference, ev or None)
    figs["trajectory"]
    return (figs,)


@app.cell
def _(figs):
    figs["map"]
    return


if __name__ == "__main__":
    app.run()
