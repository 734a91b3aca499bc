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
    import plotly.graph_objects as go

    from canopy_kit import (
        ALPHA_COLUMN,
        CONVEX_HULL_COLUMN,
        PAPER_ALPHA_M,
        accuracy_table,
        alpha_curve,
        auto_alpha,
        estimate_volume,
        estimator,
        hull_mesh,
        load_context,
        measure_tree,
        measured_points,
        plugins,
        tree_points,
        volume_column,
    )
    from canopy_kit.report.plots import plot_accuracy_matrix, plot_volumes

    return (ALPHA_COLUMN, CONVEX_HULL_COLUMN, PAPER_ALPHA_M, accuracy_table, alpha_curve,
            auto_alpha, estimate_volume, estimator, go, hull_mesh, load_context, measure_tree,
            measured_points, mo, np, plot_accuracy_matrix, plot_volumes, plt, plugins,
            tree_points, volume_column)


@app.cell
def _(load_context, mo):
    args = mo.cli_args()
    session = str(args.get("session", "out/demo/pistachio_session"))
    ctx = load_context(session, run_dir=args.get("run"), use_drone=False)
    table = ctx.table
    mo.md(f"# Canopy volumes\n\n{len(table)} trees in `{session}`.")
    return ctx, table


@app.cell
def _(ALPHA_COLUMN, CONVEX_HULL_COLUMN, ctx, plot_volumes, table, volume_column):
    # The run's recommended volume leads, as in the report.
    cols = {f"{ctx.config.volume.recommended} (recommended)": volume_column(ctx.config.volume.recommended)}
    cols |= {"convex hull": CONVEX_HULL_COLUMN, "alpha shape": ALPHA_COLUMN,
             "slices": volume_column("slices"), "true crown": "true_crown_volume_m3"}
    fig_all = plot_volumes(table, cols)
    fig_all
    return


@app.cell
def _(mo):
    # What the drive loses on tree families built four ways, against the same estimator on
    # each tree's complete foliage (benchmarks/bench_volume_families.py, held-out seeds).
    from canopy_kit import family_accuracy_table
    from canopy_kit.report.plots import plot_family_accuracy

    families = family_accuracy_table()
    mo.vstack([mo.md("## Measured accuracy on tree families\n\nThe recommended estimator "
                     "(foliage_envelope) beside the paper's two; docs/VOLUMES.md, \"Tree "
                     "families\", says what each measures."), plot_family_accuracy(families)])
    return


@app.cell
def _(accuracy_table, mo, plot_accuracy_matrix):
    # How far to trust each estimator on crowns like these: the shipped accuracy matrix
    # (benchmarks/bench_volume_matrix.py, held-out seeds, trees the pipeline segmented).
    accuracy = accuracy_table()
    fig_accuracy = plot_accuracy_matrix(accuracy)
    sensors, seeds = accuracy["sensors"].iloc[0], accuracy["seeds"].iloc[0]
    mo.vstack([mo.md(f"## Against the simulator's drawn envelopes, by crown form\n\nSensors {sensors}, seed {seeds}; "
                     "docs/VOLUMES.md explains every cell."), fig_accuracy])
    return


@app.cell
def _(PAPER_ALPHA_M, mo, plugins, table):
    tree = mo.ui.dropdown({f"{r}:{lab}": int(s) for r, lab, s in
                           zip(table["row"], table["label"], table["segment"])},
                          value=f"{table['row'].iloc[0]}:{table['label'].iloc[0]}", label="tree")
    method = mo.ui.dropdown(plugins.names("volumes"), value="alpha_shape", label="method")
    alpha = mo.ui.slider(0.2, 3.0, step=0.1, value=PAPER_ALPHA_M, label="alpha (m)",
                         show_value=True)
    mo.hstack([tree, method, alpha])
    return alpha, method, tree


@app.cell
def _(ctx, measure_tree, mo, tree, tree_points, volume_column):
    # The tree's points and volumes exactly as trees.csv measures them (map.laz grid, the
    # run's voxel thinning and estimators): this cell shows the same numbers as the table.
    xyz = tree_points(ctx.mapping.map, ctx.segmentation.labels, tree.value)
    measured = measure_tree(xyz, ctx.config.volume, ctx.segmentation.ground.height,
                            ctx.estimators)
    as_table = ", ".join(f"{m} {measured[volume_column(m)]:.2f} m³"
                         for m in dict.fromkeys([*ctx.config.volume.methods,
                                                 ctx.config.volume.recommended]))
    mo.md(f"As in trees.csv: {as_table}")
    return measured, xyz


@app.cell
def _(alpha, ctx, estimate_volume, estimator, measured_points, method, mo, np, table, tree, xyz):
    # the slider's alpha goes to every estimator that has an alpha parameter
    params = {"alpha": alpha.value} if "alpha" in estimator(method.value).get_params() else {}
    thinned = measured_points(xyz, ctx.config.volume)  # the points trees.csv measures
    result = estimate_volume(thinned, method.value, **params)
    row = table[table["segment"] == tree.value].iloc[0]
    truth = row.get("true_crown_volume_m3", np.nan)
    mo.md(f"**{method.value}**: {result.volume_m3:.2f} m³ "
          f"({'valid' if result.valid else 'flagged: ' + str(result.reason)}), "
          f"{len(thinned):,} of {len(xyz):,} points (one per "
          f"{ctx.config.volume.voxel_size:g} m voxel)"
          + (f"; true crown {truth:.2f} m³" if np.isfinite(truth) else ""))
    return thinned, truth


@app.cell
def _(PAPER_ALPHA_M, alpha_curve, auto_alpha, np, plt, thinned, truth):
    alphas = np.linspace(0.2, 4.0, 39)
    curve = alpha_curve(thinned, alphas)
    chosen = auto_alpha(thinned)
    fig_curve, ax = plt.subplots(figsize=(7, 4))
    ax.plot(curve.alphas, curve.volumes, "o-", ms=3, label="alpha shape")
    ax.axhline(curve.hull_volume, color="k", ls=":", label="convex hull")
    if np.isfinite(truth):
        ax.axhline(truth, color="tab:green", ls="--", label="true crown")
    ax.axvline(PAPER_ALPHA_M, color="tab:red", lw=0.8, label=f"paper α = {PAPER_ALPHA_M:g} m")
    ax.axvline(chosen.alpha, color="tab:purple", lw=0.8, label=f"automatic α = {chosen.alpha:.2f} m")
    ax.set_xlabel("α (m)")
    ax.set_ylabel("volume (m³)")
    ax.legend(fontsize=8)
    fig_curve
    return


@app.cell
def _(go, hull_mesh, xyz):
    # At most 10,000 points, to the centimetre, and the hull by its corners only: the page
    # stays small (the whole tree and a mesh over every point made a 3 MB output).
    corners, faces = hull_mesh(xyz)
    step = max(1, len(xyz) // 10000)
    shown = xyz[::step].round(2)
    fig3d = go.Figure([
        go.Scatter3d(x=shown[:, 0], y=shown[:, 1], z=shown[:, 2], mode="markers",
                     marker={"size": 1.5, "color": shown[:, 2], "colorscale": "Greens"},
                     name=f"points (1 in {step})"),
        go.Mesh3d(x=corners[:, 0], y=corners[:, 1], z=corners[:, 2], i=faces[:, 0],
                  j=faces[:, 1], k=faces[:, 2], opacity=0.25, color="orange",
                  name="convex hull"),
    ])
    fig3d.update_layout(scene={"aspectmode": "data"}, height=600, title="tree and its convex hull")
    fig3d
    return


if __name__ == "__main__":
    app.run()
