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


if __name__ == "__main__":
    app.run()
