"""Tables the CLI prints, readable at any terminal width and through a pipe.

A :class:`Grid` is printed (:func:`print_grid`) as a rich table when it fits the terminal;
a wider one is cut into parts that each repeat the key columns (e.g. orchard, method) and
fit; when even the key columns and one other do not fit, each row is printed as a record
(one ``column  value`` line per column). Piped or redirected (not a terminal) it is plain
tab-separated text, a ``# title`` line first, for ``cut``, ``awk`` or a spreadsheet.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from rich.console import Console
from rich.table import Table
from rich.text import Text

#: Width a boxed rich table adds: one border/separator and two padding spaces per column,
#: plus the closing border.
COLUMN_EXTRA = 3


@dataclass
class Grid:
    """A table: title, column headers, rows of cell text (rich markup allowed).

    ``keys`` leading columns are repeated in every part of a table split to fit;
    ``wrap`` columns hold prose that may wrap over lines (the others keep each value on
    one line); ``right`` columns are right-aligned; ``styles`` is one rich style per row.
    """

    columns: list[str]
    rows: list[list[str]] = field(default_factory=list)
    title: str = ""
    keys: int = 1
    right: set[int] = field(default_factory=set)
    wrap: set[int] = field(default_factory=set)
    header: bool = True
    styles: list[str] = field(default_factory=list)

    def add_row(self, *cells: Any, style: str = "") -> None:
        """Append a row (cells turned to text)."""
        self.rows.append([str(c) for c in cells])
        self.styles.append(style)


def frame_grid(frame: Any, title: str = "", keys: int = 1, digits: int = 3) -> Grid:
    """A pandas DataFrame as a :class:`Grid`: floats to ``digits`` decimals, missing as
    ``-``, numbers right-aligned, cells escaped (no markup)."""
    from rich.markup import escape

    def cell(value: Any) -> str:
        if value is None or (isinstance(value, float) and math.isnan(value)):
            return "-"
        if isinstance(value, float):
            return f"{value:.{digits}f}"
        return escape(str(value))

    numeric = {i for i, dtype in enumerate(frame.dtypes) if dtype.kind in "iuf"}
    grid = Grid([str(c) for c in frame.columns], title=title, keys=keys, right=numeric)
    for row in frame.itertuples(index=False):
        grid.add_row(*map(cell, row))
    return grid


def plain(cell: str) -> str:
    """Cell text without rich markup."""
    return Text.from_markup(cell).plain


#: Longest word a ``wrap`` column keeps on one line; longer ones (paths, module names) fold.
FOLD_WORDS_OVER = 24


def column_needs(grid: Grid) -> list[int]:
    """Width each column needs: its longest value (longest word for headers and
    ``wrap`` columns, which may wrap; at most :data:`FOLD_WORDS_OVER` for the latter)."""

    def longest_word(text: str) -> int:
        return max((len(w) for w in text.split()), default=0)

    needs = []
    for i, head in enumerate(grid.columns):
        cells = [plain(row[i]) for row in grid.rows]
        cell = (
            min(max(map(longest_word, cells), default=0), FOLD_WORDS_OVER)
            if i in grid.wrap
            else max(map(len, cells), default=0)
        )
        needs.append(max(cell, longest_word(head) if grid.header else 0, 1))
    return needs


def plan_parts(needs: Sequence[int], keys: int, width: int) -> list[list[int]] | None:
    """Column indices of each part of a table split to fit ``width``, every part starting
    with the ``keys`` key columns; None when the keys and any one other column do not fit."""
    keys = min(keys, len(needs))
    base = 1 + sum(needs[:keys]) + COLUMN_EXTRA * keys
    if base > width:
        return None
    parts: list[list[int]] = []
    current: list[int] = []
    used = base
    for i in range(keys, len(needs)):
        need = needs[i] + COLUMN_EXTRA
        if current and used + need > width:
            parts.append(current)
            current, used = [], base
        if used + need > width:
            return None
        current.append(i)
        used += need
    if current or not parts:
        parts.append(current)
    return [list(range(keys)) + part for part in parts]


def to_tsv(grid: Grid) -> str:
    """The grid as tab-separated lines (no markup; tabs and newlines in cells as spaces)."""

    def line(cells: Sequence[str]) -> str:
        return "\t".join(" ".join(plain(c).split()) for c in cells)

    lines = [f"# {plain(grid.title)}"] if grid.title else []
    if grid.header:
        lines.append(line(grid.columns))
    lines += [line(row) for row in grid.rows]
    return "\n".join(lines) + "\n"


def widen(
    needs: Sequence[int], naturals: Sequence[int], width: int, wrap: Sequence[bool] = ()
) -> list[int]:
    """Column widths from ``needs`` up to ``naturals`` (one line per header and value)
    while the table stays within ``width``: the value columns first, left to right, then
    the ``wrap`` (prose) columns a character at a time in turn."""
    widths = list(needs)
    spare = width - (1 + sum(widths) + COLUMN_EXTRA * len(widths))
    prose = [bool(wrap[i]) if i < len(wrap) else False for i in range(len(widths))]
    for i, natural in enumerate(naturals):
        if not prose[i]:
            grow = max(0, min(natural - widths[i], spare))
            widths[i] += grow
            spare -= grow
    growing = [i for i in range(len(widths)) if prose[i] and widths[i] < naturals[i]]
    while spare > 0 and growing:
        for i in list(growing):
            if spare == 0:
                break
            widths[i] += 1
            spare -= 1
            if widths[i] >= naturals[i]:
                growing.remove(i)
    return widths


def _rich_table(grid: Grid, columns: Sequence[int], width: int) -> Table:
    needs = column_needs(grid)
    naturals = [
        max(
            needs[i],
            len(grid.columns[i]) if grid.header else 0,
            max((len(plain(row[i])) for row in grid.rows), default=0),
        )
        for i in columns
    ]
    widths = widen([needs[i] for i in columns], naturals, width, [i in grid.wrap for i in columns])
    table = (
        Table(show_header=grid.header) if grid.header else Table(show_header=False, box=None)
    )  # key-value lists stay unboxed
    for i, w in zip(columns, widths):
        # A fixed width keeps rich from squeezing values: headers wrap at words, and only
        # the prose of `wrap` columns wraps.
        table.add_column(
            grid.columns[i],
            justify="right" if i in grid.right else "left",
            overflow="fold",
            width=w,
        )
    for r, row in enumerate(grid.rows):
        style = grid.styles[r] if r < len(grid.styles) else ""
        table.add_row(*(row[i] for i in columns), style=style or None)
    return table


def _records(grid: Grid) -> list[Grid]:
    """One two-column grid (column, value) per row of ``grid``."""
    out = []
    for r, row in enumerate(grid.rows):
        name = " / ".join(plain(c) for c in row[: grid.keys]) or f"row {r + 1}"
        record = Grid(
            ["column", "value"],
            title=f"{plain(grid.title)}: {name}".strip(": "),
            keys=1,
            wrap={0, 1},
            header=False,
        )
        for head, cell in zip(grid.columns, row):
            record.add_row(head, cell)
        out.append(record)
    return out


def print_grid(grid: Grid, console: Console | None = None) -> None:
    """Print ``grid`` to fit the console (see the module's docstring); TSV when piped."""
    from canopy_kit.cli.common import console as default_console

    con = console or default_console
    if not con.is_terminal:
        con.file.write(to_tsv(grid))  # as is: rich would expand the tabs
        con.file.flush()
        return
    parts = plan_parts(column_needs(grid), grid.keys, con.width)
    if parts is None and grid.keys and len(grid.columns) > 2:
        for record in _records(grid):
            print_grid(record, con)
        return
    if parts is None:  # nothing narrower: let rich fold the cells
        con.print(Text(plain(grid.title), style="bold")) if grid.title else None
        table = _rich_table(grid, range(len(grid.columns)), con.width)
        for column in table.columns:
            column.width = None
        con.print(table)
        return
    for k, columns in enumerate(parts):
        if grid.title:  # above the table, wrapped at the terminal's width, not the table's
            part = f" ({k + 1}/{len(parts)})" if len(parts) > 1 else ""
            con.print(Text(plain(grid.title) + part, style="bold"))
        con.print(_rich_table(grid, columns, con.width))
