"""Render the per-session HTML report from a jinja2 template (tables, figures, checks, config)."""

from __future__ import annotations

import html
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from canopy_kit.core.atomic import atomic_write_text
from canopy_kit.results.checks import Check, failed

__all__ = [
    "Check",
    "ReportSection",
    "render_report",
    "script_json",
    "table_html",
    "verdict",
    "write_report",
]


@dataclass
class ReportSection:
    """A titled block of figures (data URIs), optional table and free text."""

    title: str
    figures: list[tuple[str, str]] = field(default_factory=list)  # (caption, data uri)
    table: pd.DataFrame | None = None
    text: str = ""


# Degrees need more decimals than metres: 6 decimals of latitude are 0.11 m.
COLUMN_DIGITS = {"lat": 6, "lon": 6, "latitude": 6, "longitude": 6}


def table_html(
    df: pd.DataFrame,
    table_id: str,
    float_digits: int = 3,
    labels: dict[str, str] | None = None,
    row_key: str | None = None,
) -> str:
    """A sortable HTML table (click a header) with numbers right-aligned.

    Floats get ``float_digits`` decimals, geographic coordinates those of ``COLUMN_DIGITS``.
    ``labels`` gives headers for columns (the column name is kept in ``data-key`` and the
    tooltip); ``row_key`` names a column whose value each ``<tr>`` carries as ``data-id``.
    """
    labels = labels or {}
    digits = [COLUMN_DIGITS.get(str(c).lower(), float_digits) for c in df.columns]
    head = "".join(
        f'<th data-col="{i}" data-key="{html.escape(str(c))}" title="{html.escape(str(c))}">'
        f"{html.escape(labels.get(str(c), str(c)))}</th>"
        for i, c in enumerate(df.columns)
    )
    ids = df[row_key].astype(str).tolist() if row_key is not None else None
    rows = []
    for k, values in enumerate(df.itertuples(index=False, name=None)):  # keeps each column's type
        cells = []
        for v, places in zip(values, digits, strict=True):
            if isinstance(v, float):
                text = "" if pd.isna(v) else f"{v:.{places}f}"
                cells.append(f'<td class="num" data-v="{"" if pd.isna(v) else v}">{text}</td>')
            elif isinstance(v, (bool,)) or str(type(v)).endswith("bool_'>"):
                cells.append(f"<td>{'yes' if v else 'no'}</td>")
            elif isinstance(v, int) or str(type(v)).startswith("<class 'numpy.int"):
                cells.append(f'<td class="num" data-v="{v}">{v}</td>')
            else:
                cells.append(f"<td>{html.escape(str(v))}</td>")
        attr = f' data-id="{html.escape(ids[k])}"' if ids is not None else ""
        rows.append(f"<tr{attr}>" + "".join(cells) + "</tr>")
    return (
        f'<table class="sortable" id="{table_id}"><thead><tr>{head}</tr></thead>'
        f"<tbody>{''.join(rows)}</tbody></table>"
    )


def verdict(checks: list[Check]) -> dict[str, Any]:
    """The report's headline: do not trust (a check failed), caution (one warned) or fine."""
    bad = failed(checks)
    warned = [c for c in checks if c.status == "warn"]
    if bad:
        return {
            "level": "fail",
            "title": f"Do not trust this run: {len(bad)} check{'s' if len(bad) > 1 else ''} failed",
            "lines": [f"{c.name}: {c.value} ({c.threshold})" for c in bad],
        }
    if warned:
        return {
            "level": "warn",
            "title": f"Use with care: {len(warned)} "
            f"check{'s' if len(warned) > 1 else ''} warned, none failed",
            "lines": [
                f"{c.name}: {c.value}" + (f" ({c.threshold})" if c.threshold else "")
                for c in warned
            ],
        }
    return {"level": "pass", "title": "Every check passed", "lines": []}


def script_json(data: Any) -> str:
    """``data`` as JSON safe inside a ``<script type="application/json">`` element."""
    text = json.dumps(data, separators=(",", ":"), allow_nan=False)
    return text.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")


def render_report(
    title: str,
    summary: dict[str, Any],
    trees: pd.DataFrame,
    sections: list[ReportSection],
    checks: list[Check],
    config_toml: str,
    subtitle: str = "",
    provenance: dict[str, Any] | None = None,
    explorer: dict[str, Any] | None = None,
    row_table: pd.DataFrame | None = None,
) -> str:
    """The complete report page as one HTML string (CSS and JS inlined, images as data URIs).

    ``explorer`` (:func:`canopy_kit.report.explorer.explorer_data`) adds the interactive map,
    histogram, drill-down and downloads, drawn by the vendored plotly.js inlined in the page;
    ``provenance`` is shown in the header, ``row_table`` above the per-tree table.
    """
    import jinja2

    from canopy_kit.report.assets import page_script, plotly_js
    from canopy_kit.report.columns import column_label

    env = jinja2.Environment(
        loader=jinja2.PackageLoader("canopy_kit", "report/templates"),
        autoescape=jinja2.select_autoescape(["html", "j2"]),
    )
    markup = jinja2.utils.markupsafe.Markup
    template = env.get_template("report.html.j2")
    section_ctx = [
        {
            "title": s.title,
            "figures": s.figures,
            "text": s.text,
            "table": markup(table_html(s.table, f"t{i}")) if s.table is not None else None,
        }
        for i, s in enumerate(sections)
    ]
    labels = {str(c): column_label(str(c)) for c in trees.columns}
    row_key = "tree_id" if "tree_id" in trees else None
    return template.render(
        title=title,
        subtitle=subtitle,
        summary=summary,
        provenance=provenance or {},
        trees_table=markup(table_html(trees, "trees", labels=labels, row_key=row_key)),
        rows_table=markup(table_html(row_table, "rows-table")) if row_table is not None else None,
        n_trees=len(trees),
        sections=section_ctx,
        checks=checks,
        verdict=verdict(checks),
        n_passed=sum(1 for c in checks if c.status == "pass"),
        n_checks=sum(1 for c in checks if c.status in ("pass", "warn", "fail")),
        n_warned=sum(1 for c in checks if c.status == "warn"),
        n_info=sum(1 for c in checks if c.status == "info"),
        config_toml=config_toml,
        explorer=markup(script_json(explorer)) if explorer is not None else None,
        plotly_js=markup(plotly_js()) if explorer is not None else None,
        page_js=markup(page_script()),
    )


def write_report(path: str | Path, page: str) -> Path:
    """Write the page atomically."""
    return atomic_write_text(path, page)
