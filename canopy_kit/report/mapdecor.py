"""A north arrow and a scale bar for matplotlib axes drawn in metres, x east and y north."""

from __future__ import annotations

import math
from typing import Any

NICE_LENGTHS = (1, 2, 5)


def nice_length(span_m: float) -> float:
    """A round scale-bar length (1, 2 or 5 times a power of ten) near a fifth of ``span_m``."""
    if not (span_m > 0 and math.isfinite(span_m)):
        return 1.0
    target = span_m / 5
    power = 10 ** math.floor(math.log10(target))
    return max(k * power for k in NICE_LENGTHS if k * power <= target)


def add_north_arrow_and_scale(ax: Any) -> Any:
    """Draw a north arrow (top right) and a scale bar (bottom left) on ``ax``, whose data units
    are metres with y pointing north; returns ``ax``. The bar is matplotlib's AnchoredSizeBar."""
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    x0, x1 = ax.get_xlim()
    length = nice_length(abs(x1 - x0))
    label = f"{length:g} m" if length >= 1 else f"{100 * length:g} cm"
    bar = AnchoredSizeBar(
        ax.transData,
        length,
        label,
        "lower right",
        pad=0.4,
        sep=3,
        borderpad=0.6,
        frameon=True,
        size_vertical=0,
        color="black",
    )
    bar.patch.set_alpha(0.8)
    ax.add_artist(bar)
    ax.annotate(
        "N",
        xy=(0.95, 0.95),
        xytext=(0.95, 0.83),
        xycoords="axes fraction",
        ha="center",
        va="center",
        fontsize=11,
        weight="bold",
        arrowprops={"arrowstyle": "-|>", "color": "black", "lw": 1.5},
        bbox={"boxstyle": "circle,pad=0.2", "fc": "white", "ec": "none", "alpha": 0.8},
    )
    return ax
