"""Table I of Abedi et al. 2025 (17 pistachio trees) as shipped data: locate, read, validate.

The CSV keeps every value as printed text, so the number of decimals (and hence the
rounding of each printed value) survives; :func:`read_table1_text` returns that text and
:func:`load_table1` the numbers.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from canopy_kit.errors import InputError

#: Headers exactly as printed in the paper (the superscript 3 written as "³").
PRINTED_HEADERS: tuple[str, ...] = (
    "Tree Number",
    "Ground Truth Volume (m³)",
    "Convex Hull (m³)",
    "Convex Hull Error (%)",
    "Alpha Shape (m³)",
    "Alpha Shape Error (%)",
)
#: Short column names used in code, in the printed order.
COLUMNS: tuple[str, ...] = ("tree", "gt_m3", "hull_m3", "hull_err_pct", "alpha_m3", "alpha_err_pct")
#: The four value columns whose order can differ from the header in some rows.
VALUE_COLUMNS: tuple[str, ...] = COLUMNS[2:]
HEADER_OF: dict[str, str] = dict(zip(COLUMNS, PRINTED_HEADERS))
#: Table I lists seventeen trees.
N_ROWS = 17


def default_table1_path() -> Path:
    """``data/paper/table1.csv`` of the source checkout this package was imported from."""
    return Path(__file__).resolve().parents[2] / "data" / "paper" / "table1.csv"


def _resolve(path: str | Path | None) -> Path:
    resolved = Path(path) if path is not None else default_table1_path()
    if not resolved.is_file():
        hint = "" if path is not None else " (not a source checkout? pass the CSV path)"
        raise InputError(f"{resolved}: Table I file does not exist{hint}")
    return resolved


def read_table1_text(path: str | Path | None = None) -> pd.DataFrame:
    """Read and validate Table I, keeping every cell as its printed text.

    Columns are the short names of :data:`COLUMNS`; the index is the tree number.
    Raises :class:`InputError` naming the file, row and column of the first problem.
    """
    path = _resolve(path)
    try:
        raw = pd.read_csv(path, dtype=str, keep_default_na=False, encoding="utf-8")
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not a readable CSV file: {exc}") from None
    _check_headers(path, list(raw.columns))
    if len(raw) != N_ROWS:
        raise InputError(f"{path}: expected {N_ROWS} tree rows (Table I), found {len(raw)}")
    text = raw.set_axis(list(COLUMNS), axis=1).map(str.strip)
    for i, row in enumerate(text.itertuples(index=False), start=1):
        for column, cell in zip(COLUMNS, row):
            _check_cell(path, i, row[0], column, cell)
    trees = text["tree"].astype(int)
    if trees.duplicated().any():
        dup = int(trees[trees.duplicated()].iloc[0])
        raise InputError(f"{path}: tree number {dup} appears more than once")
    return text.set_index(trees.rename("tree")).drop(columns="tree")


def _check_headers(path: Path, headers: list[str]) -> None:
    stripped = [h.strip() for h in headers]
    missing = [h for h in PRINTED_HEADERS if h not in stripped]
    if missing:
        raise InputError(f"{path}: missing column {missing[0]!r} (found: {stripped})")
    extra = [h for h in stripped if h not in PRINTED_HEADERS]
    if extra:
        raise InputError(f"{path}: unexpected column {extra[0]!r}")
    if stripped != list(PRINTED_HEADERS):
        raise InputError(
            f"{path}: columns out of the printed order; expected {list(PRINTED_HEADERS)}"
        )


def _check_cell(path: Path, row: int, tree: str, column: str, cell: str) -> None:
    where = f"{path}: data row {row} (tree {tree!r}), column {HEADER_OF[column]!r}"
    if column == "tree":
        if not cell.isdigit() or int(cell) < 1:
            raise InputError(f"{where}: tree number must be a positive integer, got {cell!r}")
        return
    try:
        value = float(cell)
    except ValueError:
        raise InputError(f"{where}: not a number: {cell!r}") from None
    if not np.isfinite(value) or value <= 0:
        raise InputError(f"{where}: must be a positive number, got {cell!r}")


def load_table1(path: str | Path | None = None) -> pd.DataFrame:
    """Table I as floats (index: tree number; columns: :data:`VALUE_COLUMNS` after ``gt_m3``).

    Values are as printed, including rows whose columns are out of order; see
    :func:`canopy_kit.paper.consistency.check_table1` for the corrected table.
    """
    return read_table1_text(path).astype(float)


def printed_half_units(text: pd.DataFrame) -> pd.DataFrame:
    """Half of the last printed digit of each cell: ``"0.21"`` -> 0.005, ``"10.8"`` -> 0.05."""

    def half_unit(cell: str) -> float:
        decimals = len(cell.split(".", 1)[1]) if "." in cell else 0
        return 0.5 * 10.0 ** (-decimals)

    return text.map(half_unit)
