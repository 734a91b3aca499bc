import marimo

__generated_with = "0.25.2"
app = marimo.App(width="medium")


@app.cell
def _():
    import marimo as mo
    import matplotlib

    matplotlib.use("Agg")
    import numpy as np

    from canopy_kit import plugins
    from canopy_kit.evaluate import score_point_labels
    from canopy_kit.explore import load_context
    from canopy_kit.segment.plots import plot_failure_gallery, plot_top_view
    from canopy_kit.segment.verb import make_segmenter, segment

    return (load_context, make_segmenter, mo, np, plot_failure_gallery, plot_top_view, plugins,
            score_point_labels, segment)


@app.cell
def _(load_context, mo):
    args = mo.cli_args()
    session = str(args.get("session", "out/demo/almond_session"))
    run_dir = args.get("run")
    ctx = load_context(session, run_dir=run_dir, use_drone=False)
    mo.md(f"# Segmentation\n\nSession `{session}`: map of {len(ctx.mapping.map):,} points.")
    return (ctx,)


@app.cell
def _(mo, plugins):
    method = mo.ui.dropdown(plugins.names("segmenters"), value="dbscan", label="segmenter")
    eps = mo.ui.slider(0.3, 2.0, step=0.1, value=0.8, label="eps (m)")
    min_samples = mo.ui.slider(100, 3000, step=100, value=1300, label="min points (paper density)")
    max_cluster = mo.ui.slider(5000, 100000, step=5000, value=45000, label="spectral split above")
    # the paper's graph: every voxel point a node, k = 10; the almond-scaled preset: 0.3 m, 30
    graph_cell = mo.ui.slider(0.0, 0.5, step=0.1, value=0.0, label="graph cell (m, 0 = points)")
    neighbours = mo.ui.slider(5, 40, step=5, value=10, label="graph neighbours k")
    mo.vstack([method, mo.hstack([eps, min_samples, max_cluster]),
               mo.hstack([graph_cell, neighbours])])
    return eps, graph_cell, max_cluster, method, min_samples, neighbours


@app.cell
def _(ctx, eps, graph_cell, make_segmenter, max_cluster, method, min_samples, neighbours,
      segment):
    params = {}
    if method.value in ("dbscan", "dbscan_spectral"):
        params = {"eps": eps.value, "min_samples": min_samples.value}
    if method.value == "dbscan_spectral":
        params.update(max_cluster_size=max_cluster.value, graph_cell=graph_cell.value,
                      n_neighbors=neighbours.value)
    seg = segment(ctx.mapping.map, make_segmenter(method.value, params), ctx.config.preprocess,
                  ctx.config.rows, driving_direction=ctx.segmentation.rows.direction,
                  direction_source="trajectory")
    return (seg,)


@app.cell
def _(ctx, plot_top_view, seg):
    fig_top = plot_top_view(ctx.mapping.map, seg)
    fig_top
    return


@app.cell
def _(ctx, mo, np, score_point_labels, seg):
    truth_field = ctx.mapping.map.fields.get("tree_id")
    if truth_field is None:
        score = None
        out = mo.md("No per-point truth in this map: nothing to score.")
    else:
        score = score_point_labels(seg.labels, np.asarray(truth_field))
        d = score.to_dict()
        out = mo.md(
            f"**{d['n_correct']} of {d['n_truth']} trees** segmented one-to-one "
            f"({100 * d['success_rate']:.0f} %): merged {d['n_merged']}, split {d['n_split']}, "
            f"missed {d['n_missed']}; precision {d['precision']:.2f}, F1 {d['f1']:.2f}.")
    out
    return (score,)


@app.cell
def _(ctx, mo, np, plot_failure_gallery, score, seg):
    gallery = None
    if score is not None:
        gallery = plot_failure_gallery(ctx.mapping.map, seg, score,
                                       np.asarray(ctx.mapping.map.fields["tree_id"]))
    gallery if gallery is not None else mo.md("No failures to show.")
    return


if __name__ == "__main__":
    app.run()
