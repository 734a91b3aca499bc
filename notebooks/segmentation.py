import marimo

__generated_with = "0.25.2"
app = marimo.App(width="medium")


@app.cell
def _():
    import marimo as mo
    import matplotlib

    matplotlib.use("Agg")
    import numpy as np

    from canopy_kit import load_context, make_segmenter, plugins, score_point_labels
    from canopy_kit import segment_trees as segment
    from canopy_kit.segment.plots import plot_failure_gallery, plot_top_view

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
    # Opens on canopy-kit's own segmenter, which works on both orchards; the paper's DBSCAN
    # (and its failures on almond) are one choice away.
    method = mo.ui.dropdown(plugins.names("segmenters"), value="adaptive", label="segmenter")
    method
    return (method,)


@app.cell
def _(method, mo):
    eps = mo.ui.slider(0.3, 2.0, step=0.1, value=0.8, label="eps (m)", show_value=True)
    min_samples = mo.ui.slider(100, 3000, step=100, value=1300,
                               label="min points (paper density)", show_value=True)
    max_cluster = mo.ui.slider(5000, 100000, step=5000, value=45000,
                               label="spectral split above", show_value=True)
    # the paper's graph: every voxel point a node, k = 10; the almond-scaled preset: 0.3 m, 30
    graph_cell = mo.ui.slider(0.0, 0.5, step=0.1, value=0.0, label="graph cell (m, 0 = points)",
                              show_value=True)
    neighbours = mo.ui.slider(5, 40, step=5, value=10, label="graph neighbours k",
                              show_value=True)
    _controls = []
    if method.value in ("dbscan", "dbscan_spectral"):
        _controls.append(mo.hstack([eps, min_samples]))
    if method.value == "dbscan_spectral":
        _controls.append(mo.hstack([max_cluster, graph_cell, neighbours]))
    mo.vstack(_controls) if _controls else mo.md(
        f"`{method.value}` runs with its own settings (no sliders).")
    return eps, graph_cell, max_cluster, min_samples, neighbours


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
def _(mo, score):
    # One failed tree at a time: a gallery of all of them outgrows marimo's output limit.
    failures = score.failures() if score is not None else {}
    failed_tree = mo.ui.dropdown(failures, value=next(iter(failures), None),
                                 label="tree not segmented correctly (lowest IoU first)")
    failed_tree if failures else mo.md("No failures to show." if score is not None else "")
    return (failed_tree,)


@app.cell
def _(ctx, failed_tree, mo, np, plot_failure_gallery, score, seg):
    mo.stop(score is None or failed_tree.value is None)
    gallery = plot_failure_gallery(ctx.mapping.map, seg, score.only(failed_tree.value),
                                   np.asarray(ctx.mapping.map.fields["tree_id"]),
                                   max_panels=1, max_points=15_000)
    gallery
    return


if __name__ == "__main__":
    app.run()
