import marimo

__generated_with = "0.25.2"
app = marimo.App(width="medium")


@app.cell
def _():
    import marimo as mo
    import matplotlib

    matplotlib.use("Agg")

    from canopy_kit import ALPHA_COLUMN, CONVEX_HULL_COLUMN, load_context, volume_column
    from canopy_kit.report.plots import plot_agreement
    from ground_truth.plots import plot_crowns, plot_surface

    return (ALPHA_COLUMN, CONVEX_HULL_COLUMN, load_context, mo, plot_agreement, plot_crowns,
            plot_surface, volume_column)


@app.cell
def _(load_context, mo):
    args = mo.cli_args()
    session = str(args.get("session", "out/demo/pistachio_session"))
    ctx = load_context(session, run_dir=args.get("run"), use_drone=True)
    aerial = ctx.aerial
    mo.md(f"# Aerial ground truth\n\nSession `{session}`: "
          + ("no drone photos in this session." if aerial is None else
             f"{len(aerial.crowns)} crowns delineated from the drone photos."))
    return aerial, ctx


@app.cell
def _(aerial, mo, plot_crowns):
    ax_ortho = plot_crowns(aerial.ortho, aerial.segmentation, aerial.crowns) if aerial else None
    ax_ortho.figure if ax_ortho is not None else mo.md("")
    return


@app.cell
def _(aerial, mo, plot_surface):
    axes = plot_surface(aerial.surface) if aerial else None
    axes[0].figure if axes is not None else mo.md("")
    return


@app.cell
def _(ALPHA_COLUMN, CONVEX_HULL_COLUMN, ctx, mo, volume_column):
    # The run's recommended volume first (the headline everywhere), the paper's beside it.
    recommended = f"{ctx.config.volume.recommended} (recommended)"
    choices = {recommended: volume_column(ctx.config.volume.recommended)}
    choices |= {"alpha shape": ALPHA_COLUMN, "convex hull": CONVEX_HULL_COLUMN}
    source = mo.ui.dropdown(choices, value=recommended, label="LiDAR volume")
    reference = mo.ui.dropdown({"aerial sphere (paper)": "aerial_sphere_volume_m3",
                                "aerial ellipsoid": "aerial_ellipsoid_volume_m3",
                                "true crown (simulator)": "true_crown_volume_m3"},
                               value="aerial sphere (paper)", label="reference")
    mo.hstack([source, reference])
    return reference, source


@app.cell
def _(ctx, mo, plot_agreement, reference, source):
    t = ctx.table
    ok = t[source.value].notna() & t.get(reference.value, t[source.value] * float("nan")).notna()
    sub = t[ok]
    fig_ag = (plot_agreement(sub[source.value].to_numpy(), sub[reference.value].to_numpy(),
                             (source.selected_key, reference.selected_key), list(sub["label"]))
              if len(sub) >= 2 else None)
    fig_ag if fig_ag is not None else mo.md("Fewer than two matched trees.")
    return


if __name__ == "__main__":
    app.run()
