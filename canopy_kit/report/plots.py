"""Figures for the session report and the notebooks (matplotlib, arrays and tables in)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd


def _axes(ax: Any, size: tuple[float, float] = (8, 6)) -> tuple[Any, Any]:
    import matplotlib.pyplot as plt

    if ax is None:
        fig, ax = plt.subplots(figsize=size)
        return fig, ax
    return ax.figure, ax


def plot_volumes(trees: pd.DataFrame, columns: dict[str, str], ax: Any = None) -> Any:
    """Grouped bars of each tree's volume by method (``columns``: label -> column)."""
    fig, ax = _axes(ax, (max(6, 0.35 * len(trees) + 2), 4.5))
    cols = {k: v for k, v in columns.items() if v in trees}
    x = np.arange(len(trees))
    width = 0.8 / max(len(cols), 1)
    for i, (name, col) in enumerate(cols.items()):
        ax.bar(x + (i - (len(cols) - 1) / 2) * width, trees[col], width, label=name)
    ax.set_xticks(x)
    names = (
        trees["tree_id"] if "tree_id" in trees else trees["row"].astype(str) + "-" + trees["label"]
    )
    ax.set_xticklabels(names.astype(str), rotation=90, fontsize=9)
    ax.set_ylabel("volume (m³)")
    ax.legend(fontsize=8)
    ax.set_title("canopy volume per tree")
    return fig


def plot_agreement(
    estimate: np.ndarray,
    reference: np.ndarray,
    names: tuple[str, str],
    labels: list[str] | None = None,
) -> Any:
    """Scatter against the 1:1 line and a Bland-Altman plot, side by side."""
    import matplotlib.pyplot as plt

    from canopy_kit.evaluate import stats

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.5))
    est, ref = np.asarray(estimate, float), np.asarray(reference, float)
    lim = [0, 1.05 * max(np.nanmax(est), np.nanmax(ref))]
    a.plot(lim, lim, "k--", lw=0.8)
    a.scatter(ref, est, s=18)
    if labels is not None:
        for x, y, lab in zip(ref, est, labels):
            a.annotate(lab, (x, y), fontsize=8, xytext=(2, 2), textcoords="offset points")
    ag = stats.agreement(est, ref)
    a.set_xlabel(f"{names[1]} (m³)")
    a.set_ylabel(f"{names[0]} (m³)")
    a.set_title(f"MAPE {ag.mape_pct:.1f} %, R² {ag.r_squared:.2f}")
    a.set_xlim(lim)
    a.set_ylim(lim)
    mean, diff = (est + ref) / 2, est - ref
    ba = ag.bland_altman
    b.scatter(mean, diff, s=18)
    for y, style in ((ba.mean_difference, "-"), (ba.lower_limit, "--"), (ba.upper_limit, "--")):
        b.axhline(y, color="tab:red", ls=style, lw=0.8)
    b.set_xlabel("mean of the two (m³)")
    b.set_ylabel("difference (m³)")
    b.set_title("Bland-Altman (mean and 95 % limits)")
    fig.tight_layout()
    return fig


def _bias_panel(
    ax: Any,
    rows: pd.DataFrame,
    groups: list[str],
    methods: list[str] | tuple[str, ...],
    goal: tuple[float, float],
    labels: list[str],
    title: str,
) -> list[tuple[np.ndarray, list[tuple[str, str]]]]:
    """One panel: per group (``rows`` indexed by (group, method)) each method's signed bias
    (bar) and MAPE (dot) in %, the goal's lines; returns each method's bar positions and cells."""
    x = np.arange(len(groups))
    width = 0.8 / max(len(methods), 1)
    drawn = []
    for i, method in enumerate(methods):
        offset = x + (i - (len(methods) - 1) / 2) * width
        cells = [(group, method) for group in groups]
        bias = [100 * rows["bias"].get(c, np.nan) for c in cells]
        mape = [100 * rows["mape"].get(c, np.nan) for c in cells]
        bars = ax.bar(offset, bias, width, label=f"{method}: bias")
        ax.plot(offset, mape, "o", color=bars.patches[0].get_facecolor(), mec="black", ms=5)
        drawn.append((offset, cells))
    ax.axhline(0, color="black", lw=0.8)
    for level, style in ((goal[0], "--"), (-goal[0], "--"), (goal[1], ":")):
        ax.axhline(100 * level, color="grey", lw=0.8, ls=style)
    ax.set_xticks(x)
    ax.set_xticklabels(labels)
    ax.set_title(title)
    ax.grid(axis="y", alpha=0.3)
    return drawn


def plot_accuracy_matrix(table: pd.DataFrame, goal: tuple[float, float] = (0.05, 0.08)) -> Any:
    """Per crown form, each estimator's signed bias (bar) and MAPE (dot) against the true crown
    volume, one panel per scan (both sides, one side), from the accuracy table
    (``canopy_kit.volume.accuracy.accuracy_table``); ``goal``: the |bias| and MAPE bars drawn."""
    import matplotlib.pyplot as plt

    forms = [f for f in table["form"].unique() if f not in ("all", "dense")]
    scans = list(table["scan"].unique())
    methods = list(table["method"].unique())
    fig, axes = plt.subplots(1, len(scans), figsize=(5.5 * len(scans), 4.2), sharey=True)
    axes = np.atleast_1d(axes)
    for ax, scan in zip(axes, scans, strict=True):
        rows = table[table["scan"] == scan].set_index(["form", "method"])
        _bias_panel(ax, rows, forms, methods, goal, forms, f"scan: {scan}")
    return _finish_bias_figure(
        fig,
        axes,
        "error against the true volume (%)",
        f"Volume accuracy by crown form (dashed: ±{100 * goal[0]:.0f} % bias, "
        f"dotted: {100 * goal[1]:.0f} % MAPE)",
    )


def _finish_bias_figure(fig: Any, axes: np.ndarray, ylabel: str, title: str) -> Any:
    """Label, legend and title a row of :func:`_bias_panel` panels."""
    axes[0].set_ylabel(f"{ylabel}\nbar: signed bias, dot: MAPE")
    axes[0].legend(fontsize=8, loc="lower left")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def plot_family_accuracy(
    table: pd.DataFrame,
    methods: tuple[str, ...] = ("foliage_envelope", "alpha_shape", "convex_hull"),
    goal: tuple[float, float] = (0.05, 0.08),
) -> Any:
    """Per tree family (old trees), each estimator's scan-induced signed bias (bar) and MAPE
    (dot) against the same estimator on the complete foliage, one panel per side, from the
    family accuracy table (``canopy_kit.volume.accuracy.family_accuracy_table``); the first
    method's interval coverage is written under its bars; ``goal``: the |bias| and MAPE lines."""
    import matplotlib.pyplot as plt

    old = table[(table["age"] == "old") & table["method"].isin(methods)]
    families = list(dict.fromkeys(old["family"]))
    sides = [s for s in ("both", "one") if s in set(old["side"])]
    fig, axes = plt.subplots(1, len(sides), figsize=(5.5 * len(sides), 4.2), sharey=True)
    axes = np.atleast_1d(axes)
    labels = [f.replace("_", " ") for f in families]
    for ax, side in zip(axes, sides, strict=True):
        rows = old[old["side"] == side].set_index(["family", "method"])
        title = f"scan: {'both sides' if side == 'both' else 'one side'}"
        offsets, cells = _bias_panel(ax, rows, families, methods, goal, labels, title)[0]
        for xo, cell in zip(offsets, cells, strict=True):
            cover = rows["interval_covers"].get(cell, np.nan)
            if np.isfinite(cover):
                ax.annotate(
                    f"{cover:.0%}",
                    (xo, 0),
                    xytext=(0, -14),
                    textcoords="offset points",
                    ha="center",
                    fontsize=8,
                )
    return _finish_bias_figure(
        fig,
        axes,
        "drive against complete foliage (%)",
        f"What the drive loses, per tree family (held-out seeds; under the bars: how often "
        f"{methods[0]}'s interval held the value)",
    )


MAX_PROFILE_ROWS = 12  # rows drawn by plot_row_profiles (a figure stays readable)


def plot_row_profiles(
    sections: pd.DataFrame, summary: pd.DataFrame | None = None, max_rows: int = MAX_PROFILE_ROWS
) -> Any:
    """Per row (the first ``max_rows``), a side view of the canopy height and a top view of
    its left and right width about the fitted row line, per section along the row, from a
    row profile's sections table (``canopy_kit.segment.row_profile``); ``summary`` adds each
    row's TRV and LWA to its title."""
    import matplotlib.pyplot as plt

    rows = [int(r) for r in dict.fromkeys(sections["row"])] if len(sections) else []
    shown = rows[:max_rows]
    n = max(len(shown), 1)
    # 7 in wide: the report shows figures at most 640 px wide, so 9 pt stays about 11 px.
    fig, axes = plt.subplots(n, 2, figsize=(7, 2.1 * n + 0.8), squeeze=False)
    if not shown:
        for ax in axes[0]:
            ax.text(0.5, 0.5, "no row holds canopy", ha="center", va="center", fontsize=10)
            ax.set_axis_off()
        return fig
    info = summary.set_index("row") if summary is not None and len(summary) else None
    top_h = float(np.nanmax(sections["height_m"])) if len(sections) else 1.0
    wide = np.nanmax(np.abs(sections[["width_left_m", "width_right_m"]].to_numpy()))
    wide = float(wide) if np.isfinite(wide) and wide > 0 else 1.0
    for (side, top), row in zip(axes, shown, strict=True):
        t = sections[sections["row"] == row]
        edges = np.r_[t["start_m"].to_numpy(), t["end_m"].to_numpy()[-1:]]
        height = np.r_[t["height_m"].to_numpy(), t["height_m"].to_numpy()[-1:]]
        left = np.r_[t["width_left_m"].to_numpy(), t["width_left_m"].to_numpy()[-1:]]
        right = np.r_[t["width_right_m"].to_numpy(), t["width_right_m"].to_numpy()[-1:]]
        side.fill_between(edges, 0, height, step="post", color="tab:green", alpha=0.5)
        side.step(edges, height, where="post", color="darkgreen", lw=1)
        side.set_ylim(0, 1.1 * top_h)
        side.set_ylabel("height (m)", fontsize=9)
        top.fill_between(edges, -left, right, step="post", color="tab:green", alpha=0.5)
        top.step(edges, right, where="post", color="darkgreen", lw=1, label="right")
        top.step(edges, -left, where="post", color="tab:brown", lw=1, label="left")
        top.axhline(0, color="black", lw=0.8, ls="--")
        top.set_ylim(-1.1 * wide, 1.45 * wide)
        top.set_ylabel("left - / right + (m)", fontsize=9)
        title = f"row {row}: height"
        if info is not None and row in info.index:
            trv = info.loc[row, "trv_m3_per_ha"]
            if np.isfinite(trv):
                title += f" (TRV {trv:,.0f} m³/ha)"
        side.set_title(title, fontsize=9)
        top.set_title(f"row {row}: width about the row line", fontsize=9)
        for ax in (side, top):
            ax.tick_params(labelsize=8)
            ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("along the row (m)", fontsize=9)
    axes[0, 1].legend(fontsize=8, loc="upper right", ncol=2)
    if len(rows) > len(shown):
        fig.suptitle(f"first {len(shown)} of {len(rows)} rows (all in rows.csv)", fontsize=10)
    fig.tight_layout()
    return fig
