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

    from canopy_kit.paper.consistency import check_table1
    from canopy_kit.paper.summary import summarise_table1
    from canopy_kit.report.plots import plot_agreement

    return check_table1, mo, np, plot_agreement, plt, summarise_table1


@app.cell
def _(mo):
    mo.md(
        """
        # Reproducing Abedi et al. 2025

        Table I of the paper, transcribed as printed (`data/paper/table1.csv`), checked
        row by row, corrected where its columns are in another order than the header says,
        and summarised with the statistics the paper does not give.
        """
    )
    return


@app.cell
def _(mo):
    reading = mo.ui.dropdown(["corrected", "as_printed"], value="corrected", label="Table reading")
    reading
    return (reading,)


@app.cell
def _(check_table1, reading, summarise_table1):
    check = check_table1()
    summary = summarise_table1(check, reading.value)
    table = check.corrected if reading.value == "corrected" else check.as_printed
    return check, summary, table


@app.cell
def _(check, mo):
    findings = [
        f"tree {r.tree}: " + ", ".join(f"'{h}' holds {a}" for h, a in r.moved_columns())
        for r in check.findings
    ]
    mo.md("## Inconsistent rows found from the numbers\n\n" + "\n".join(f"- {f}" for f in findings))
    return


@app.cell
def _(mo, summary):
    rows = []
    for method, a in summary.agreement.items():
        d = a.as_dict()
        rows.append({"method": method, **{k: round(v, 3) if isinstance(v, float) else v
                                          for k, v in d.items()}})
    mo.vstack([
        mo.md(f"## Agreement with the aerial sphere volumes ({summary.reading})"),
        mo.ui.table(rows, selection=None),
        mo.md(f"Alpha shape better than convex hull for **{len(summary.claim.alpha_better)} of "
              f"{summary.claim.n_trees}** trees (the paper says 'consistently')."),
    ])
    return


@app.cell
def _(plot_agreement, table):
    fig_alpha = plot_agreement(table["alpha_m3"].to_numpy(), table["gt_m3"].to_numpy(),
                               ("alpha shape", "aerial sphere"),
                               [str(t) for t in table.index])
    fig_alpha
    return


@app.cell
def _(np, plt, table):
    fig_err, ax = plt.subplots(figsize=(9, 3.5))
    x = np.arange(len(table))
    ax.bar(x - 0.2, table["hull_err_pct"], 0.4, label="convex hull")
    ax.bar(x + 0.2, table["alpha_err_pct"], 0.4, label="alpha shape")
    ax.set_xticks(x)
    ax.set_xticklabels(table.index)
    ax.set_xlabel("tree")
    ax.set_ylabel("error vs aerial (%)")
    ax.legend()
    fig_err
    return


@app.cell
def _(mo, summary):
    mo.vstack([mo.md("## Crown diameters implied by the sphere volumes"),
               mo.ui.table(summary.diameters.reset_index(), selection=None)])
    return


@app.cell
def _(mo):
    mo.md(
        """
        ## The experiments, re-run on simulated orchards

        The committed results (`data/paper/experiments*.{csv,json}`), or those a run of
        `canopy-kit paper experiments` saved in the folder given as `-- --results DIR`
        (it writes a new `out/paper-YYYYmmdd-HHMMSS`); this notebook only reads them, it never
        re-runs a simulation. Segmentation success: a true tree counts when one segment
        matches it one to one with point IoU >= 0.5. Volume errors are taken on the correctly
        segmented trees, against the aerial sphere π d³/6 of the widest true crown diameter
        (the paper's ground truth) and against the true crown volume.
        """
    )
    return


@app.cell
def _(mo):
    from canopy_kit.errors import InputError
    from canopy_kit.paper.experiments import load_results

    try:
        experiments = load_results(mo.cli_args().get("results"))
        _seeds = "; ".join(
            f"{_o} seeds {', '.join(str(int(_s)) for _s in sorted(set(_g['seed'])))}"
            for _o, _g in experiments.runs.groupby("orchard", sort=False))
        experiments_note = mo.md(
            f"Results of {len(experiments.runs)} runs ({_seeds}), "
            f"{experiments.config.rows} rows x {experiments.config.trees_per_row} trees per "
            f"session, mapping {', '.join(experiments.config.mappings)}.")
    except InputError as exc:
        experiments = None
        experiments_note = mo.callout(mo.md(
            f"No saved experiment results ({exc}). Run `canopy-kit paper experiments` to make them "
            "(hours: it simulates and maps every session) and give its folder as "
            "`-- --results DIR`."),
            kind="warn")
    experiments_note
    return (experiments,)


@app.cell
def _(experiments, mo):
    mo.stop(experiments is None)
    _cols = ["orchard", "method", "mapping", "paper_success_pct", "success_pct",
             "success_min_pct", "success_max_pct", "n_correct", "n_truth",
             "paper_convex_hull_mape_vs_sphere_pct", "convex_hull_mape_vs_sphere_pct",
             "paper_alpha_shape_mape_vs_sphere_pct", "alpha_shape_mape_vs_sphere_pct",
             "convex_hull_mape_vs_crown_pct", "alpha_shape_mape_vs_crown_pct",
             "convex_hull_bias_vs_sphere_pct", "alpha_shape_bias_vs_sphere_pct",
             "convex_hull_bias_vs_crown_pct", "alpha_shape_bias_vs_crown_pct",
             "paper_alpha_better", "alpha_better_vs_sphere", "alpha_better_vs_crown",
             "n_trees_vs_sphere"]
    _table = experiments.comparison.reindex(columns=_cols).round(1)
    mo.vstack([mo.md("### Paper beside reproduction"), mo.ui.table(_table, selection=None)])
    return


@app.cell
def _(experiments, mo, np, plt):
    mo.stop(experiments is None)
    _c = experiments.comparison
    _mappings = list(experiments.config.mappings)
    fig_experiments, (_ax_seg, _ax_vol) = plt.subplots(1, 2, figsize=(13, 4.2))
    # Segmentation: paper vs ours for every orchard x method, per mapping.
    _pairs = list(dict.fromkeys(zip(_c["orchard"], _c["method"])))
    _x = np.arange(len(_pairs))
    _w = 0.8 / (1 + len(_mappings))
    _paper = [_c[(_c["orchard"] == o) & (_c["method"] == m)]["paper_success_pct"].iloc[0]
              for o, m in _pairs]
    _ax_seg.bar(_x - 0.4 + _w / 2, _paper, _w, color="0.6", label="paper")
    for _k, _mapping in enumerate(_mappings):
        _rows = [_c[(_c["orchard"] == o) & (_c["method"] == m) & (_c["mapping"] == _mapping)].iloc[0]
                 for o, m in _pairs]
        _mean = np.array([r["success_pct"] for r in _rows], float)
        _lo = np.array([r["success_min_pct"] for r in _rows], float)
        _hi = np.array([r["success_max_pct"] for r in _rows], float)
        _ax_seg.bar(_x - 0.4 + _w * (_k + 1.5), _mean, _w, label=f"ours ({_mapping} map)",
                    yerr=np.vstack([_mean - _lo, _hi - _mean]), capsize=3)
    _ax_seg.set_xticks(_x)
    _ax_seg.set_xticklabels([f"{o}\n{m}" for o, m in _pairs], fontsize=8)
    _ax_seg.set_ylabel("trees correctly segmented (%)")
    _ax_seg.set_ylim(0, 105)
    _ax_seg.set_title("Segmentation success (bars: seed range)")
    _ax_seg.legend(fontsize=8)
    # Volumes of the paper's configuration: pistachio, DBSCAN.
    _labels = ["hull vs sphere", "alpha vs sphere", "hull vs crown", "alpha vs crown"]
    _keys = ["convex_hull_mape_vs_sphere_pct", "alpha_shape_mape_vs_sphere_pct",
             "convex_hull_mape_vs_crown_pct", "alpha_shape_mape_vs_crown_pct"]
    _sel = _c[(_c["orchard"] == "pistachio") & (_c["method"] == "dbscan")]
    _x = np.arange(len(_keys))
    if len(_sel):
        _first = _sel.iloc[0]
        _ax_vol.bar(_x - 0.4 + _w / 2, [_first.get(f"paper_{k}", np.nan) for k in _keys], _w,
                    color="0.6", label="paper (Table I)")
        for _k, (_, _row) in enumerate(_sel.iterrows()):
            _ax_vol.bar(_x - 0.4 + _w * (_k + 1.5), [_row.get(k, np.nan) for k in _keys], _w,
                        label=f"ours ({_row['mapping']} map)")
    _ax_vol.set_xticks(_x)
    _ax_vol.set_xticklabels(_labels, fontsize=8)
    _ax_vol.set_ylabel("MAPE (%)")
    _ax_vol.set_title("Volume error, pistachio + DBSCAN (the paper has no crown truth)")
    _ax_vol.legend(fontsize=8)
    fig_experiments.tight_layout()
    fig_experiments
    return


if __name__ == "__main__":
    app.run()
