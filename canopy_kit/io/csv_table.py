"""Tables as CSV a person and a spreadsheet read: numbers rounded to what they mean, and a
W3C CSV on the Web metadata sidecar (``<name>.csv-metadata.json``) with the provenance.

A coordinate in metres is stored to the millimetre (the map's LAS grid), a latitude or
longitude to 1e-8 degree (about 1 mm), areas and volumes to 1e-3 m² / m³, percentages to
1e-2, other measured numbers to six significant digits: the float noise of the arithmetic
(``3.9250000000000003``) is not written. The sidecar follows the CSVW metadata vocabulary
(https://www.w3.org/TR/tabular-metadata/): the CSV stays a plain table for pandas and
spreadsheets, and the provenance (bag, its hash, software, preset) travels beside it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from canopy_kit.core.atomic import atomic_write_text

SIGNIFICANT_DIGITS = 6  # numbers without a unit the name states
# (suffix of a column name, decimals, unit) in the order they are tried
UNIT_SUFFIXES: tuple[tuple[str, int, str], ...] = (
    ("_m3", 3, "m³"),
    ("_m2", 3, "m²"),
    ("_pct", 2, "%"),
    ("_deg", 4, "°"),
    ("_s", 3, "s"),
    ("_m", 3, "m"),
)
NAMED_DECIMALS: dict[str, tuple[int, str]] = {
    "lat": (8, "°"),
    "lon": (8, "°"),
    "x": (3, "m"),
    "y": (3, "m"),
    "z": (3, "m"),
}


def column_rounding(name: str) -> tuple[int | None, str]:
    """Decimals a column is written with (None: six significant digits) and its unit."""
    if name in NAMED_DECIMALS:
        return NAMED_DECIMALS[name]
    for suffix, decimals, unit in UNIT_SUFFIXES:
        if name.endswith(suffix):
            return decimals, unit
    return None, ""


def _significant(values: np.ndarray, digits: int) -> np.ndarray:
    finite = np.isfinite(values) & (values != 0)
    out = values.copy()
    scale = np.floor(np.log10(np.abs(values[finite])))
    factor = 10.0 ** (digits - 1 - scale)
    out[finite] = np.round(values[finite] * factor) / factor
    return out


def rounded(table: pd.DataFrame) -> pd.DataFrame:
    """``table`` with each float column rounded to its meaning (module docstring)."""
    out = table.copy()
    for name in out.columns:
        if not pd.api.types.is_float_dtype(out[name]):
            continue
        values = out[name].to_numpy(dtype=np.float64)
        decimals, _ = column_rounding(str(name))
        if decimals is None:
            out[name] = _significant(values, SIGNIFICANT_DIGITS)
        else:
            out[name] = np.round(values, decimals)
    return out


def csv_text(table: pd.DataFrame) -> str:
    """The CSV text of ``table``, rounded (:func:`rounded`), shortest exact decimals."""
    return rounded(table).to_csv(index=False, lineterminator="\n")


def _datatype(series: pd.Series) -> str:
    if pd.api.types.is_bool_dtype(series):
        return "boolean"
    if pd.api.types.is_integer_dtype(series):
        return "integer"
    if pd.api.types.is_float_dtype(series):
        return "double"
    return "string"


def csvw_metadata(
    table: pd.DataFrame,
    csv_name: str,
    provenance: dict[str, Any] | None = None,
    title: str = "",
) -> dict[str, Any]:
    """CSVW table metadata of ``table`` written as ``csv_name``: columns with their datatype
    and unit, the provenance under ``prov:wasGeneratedBy``."""
    from canopy_kit import __version__

    columns = []
    for name in table.columns:
        column: dict[str, Any] = {
            "name": str(name),
            "titles": str(name),
            "datatype": _datatype(table[name]),
        }
        decimals, unit = column_rounding(str(name))
        if unit and column["datatype"] == "double":
            column["schema:unitText"] = unit
        if column["datatype"] == "double":
            column["dc:description"] = (
                f"rounded to {decimals} decimals"
                if decimals is not None
                else f"rounded to {SIGNIFICANT_DIGITS} significant digits"
            )
        columns.append(column)
    meta: dict[str, Any] = {
        "@context": "http://www.w3.org/ns/csvw",
        "url": csv_name,
        "dc:creator": f"canopy-kit {__version__}",
        "tableSchema": {"columns": columns},
    }
    if title:
        meta["dc:title"] = title
    if provenance:
        meta["prov:wasGeneratedBy"] = dict(provenance)
    return meta


def metadata_path(csv_path: str | Path) -> Path:
    """Where the CSVW sidecar of ``csv_path`` is written (``trees.csv-metadata.json``)."""
    path = Path(csv_path)
    return path.with_name(path.name + "-metadata.json")


def write_csv_table(
    table: pd.DataFrame,
    path: str | Path,
    provenance: dict[str, Any] | None = None,
    title: str = "",
) -> dict[str, Path]:
    """Write ``table`` as rounded CSV and its CSVW sidecar, each atomically; the paths by name."""
    path = Path(path)
    sidecar = metadata_path(path)
    meta = csvw_metadata(table, path.name, provenance, title)
    atomic_write_text(path, csv_text(table))
    atomic_write_text(sidecar, json.dumps(meta, indent=1, default=str) + "\n")
    return {path.name: path, sidecar.name: sidecar}


def is_number_text(text: str) -> bool:
    """Whether a table cell's text reads as a number (a headerless table's first row)."""
    try:
        float(text)
    except ValueError:
        return False
    return True
