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

    from canopy_kit import plugins
    from canopy_kit.explore import load_context
    from canopy_kit.report.plots import plot_volumes
    from canopy_kit.volume import alpha_curve, auto_alpha, estimate_volume
    from canopy_kit.volume.hull import hull_mesh

    return (alpha_curve, auto_alpha, estimate_volume, go, hull_mesh, load_context, mo, np,
            plot_volumes, plt, plugins)


@app.cell
def _(load_context, mo):
    args = mo.cli_args()
    session = str(args.get("session", "out/demo/pistachio_session"))
    ctx = load_context(session, run_dir=args.get("run"), use_drone=False)
    table = ctx.table
    mo.md(f"# Canopy volumes\n\n{len(table)} trees in `{session}`.")
    return ctx, table


@app.cell
def _(plot_volumes, table):
    cols = {"convex hull": "volume_convex_hull_m3", "alpha shape": "volume_alpha_m3",
            "slices": "volume_slices_m3", "true crown": "true_crown_volume_m3"}
    fig_all = plot_volumes(table, cols)
    fig_all
    return


@app.cell
def _(mo, plugins, table):
    tree = mo.ui.dropdown({f"{r}:{lab}": int(s) for r, lab, s in
                           zip(table["row"], table["label"], table["segment"])},
                          value=f"{table['row'].iloc[0]}:{table['label'].iloc[0]}", label="tree")
    method = mo.ui.dropdown(plugins.names("volumes"), value="alpha_shape", label="method")
    alpha = mo.ui.slider(0.2, 3.0, step=0.1, value=0.9, label="alpha (m)", show_value=True)
    mo.hstack([tree, method, alpha])
    return alpha, method, tree


@app.cell
def _(alpha, ctx, estimate_volume, method, mo, np, table, tree):
    xyz = ctx.mapping.map.xyz[ctx.segmentation.labels == tree.value]
    params = {"alpha": alpha.value} if method.value in ("alpha_shape", "alpha_hull") else {}
    result = estimate_volume(xyz, method.value, **params)
    row = table[table["segment"] == tree.value].iloc[0]
    truth = row.get("true_crown_volume_m3", np.nan)
    mo.md(f"**{method.value}**: {result.volume_m3:.2f} m³ "
          f"({'valid' if result.valid else 'flagged: ' + str(result.reason)}), "
          f"{len(xyz):,} points" + (f"; true crown {truth:.2f} m³" if np.isfinite(truth) else ""))
    return truth, xyz


@app.cell
def _(alpha_curve, auto_alpha, np, plt, truth, xyz):
    alphas = np.linspace(0.2, 4.0, 39)
    curve = alpha_curve(xyz, alphas)
    chosen = auto_alpha(xyz)
    fig_curve, ax = plt.subplots(figsize=(7, 4))
    ax.plot(curve.alphas, curve.volumes, "o-", ms=3, label="alpha shape")
    ax.axhline(curve.hull_volume, color="k", ls=":", label="convex hull")
    if np.isfinite(truth):
        ax.axhline(truth, color="tab:green", ls="--", label="true crown")
    ax.axvline(0.9, color="tab:red", lw=0.8, label="paper α = 0.9 m")
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
