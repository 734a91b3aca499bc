"""Tables written as CSV: rounded to each column's meaning, with a CSVW sidecar holding the
provenance; read back by pandas unchanged in shape, and by the csv module as plain text."""

from __future__ import annotations

import csv
import json

import numpy as np
import pandas as pd

from canopy_kit.io.csv_table import column_rounding, metadata_path, rounded, write_csv_table


def _table() -> pd.DataFrame:
    return pd.DataFrame(
        {
            "tree_id": ["r0-L0", "r0-L1"],
            "row": [0, 0],
            "x": [3.9250000000000003, -12.34567891],
            "lat": [38.123456789012345, 38.1234567],
            "lon": [-121.98765432109876, np.nan],
            "height_m": [4.00049, 3.9996],
            "volume_alpha_m3": [12.34567, 0.0004],
            "error_alpha_vs_true_pct": [-3.14159, 12.0],
            "surface_fill": [1.23456789, 0.000123456789],
        }
    )


def test_numbers_are_rounded_to_their_meaning() -> None:
    out = rounded(_table())
    assert out["x"].tolist() == [3.925, -12.346]  # mm
    assert out["lat"].tolist() == [38.12345679, 38.1234567]  # 1e-8 degree
    assert out["lon"].iloc[0] == -121.98765432 and np.isnan(out["lon"].iloc[1])
    assert out["height_m"].tolist() == [4.0, 4.0]
    assert out["volume_alpha_m3"].tolist() == [12.346, 0.0]  # a litre
    assert out["error_alpha_vs_true_pct"].tolist() == [-3.14, 12.0]
    assert out["surface_fill"].tolist() == [1.23457, 0.000123457]  # six significant digits
    assert out["row"].dtype == np.int64 and out["tree_id"].tolist() == ["r0-L0", "r0-L1"]
    assert column_rounding("crown_diameter_m") == (3, "m")
    assert column_rounding("projected_area_m2") == (3, "m²")
    assert column_rounding("n_points") == (None, "")


def test_csv_and_its_sidecar(tmp_path) -> None:
    provenance = {"orchard": "block 7", "bag_sha256": "ab" * 32, "software_version": "0.1.0"}
    files = write_csv_table(_table(), tmp_path / "trees.csv", provenance, "per-tree table")
    assert sorted(files) == ["trees.csv", "trees.csv-metadata.json"]
    text = (tmp_path / "trees.csv").read_text()
    assert "3.9250000000000003" not in text and "3.925," in text
    rows = list(csv.reader(text.splitlines()))
    assert rows[0] == list(_table().columns) and len(rows) == 3  # no comment lines
    back = pd.read_csv(tmp_path / "trees.csv")
    assert back.shape == _table().shape
    assert np.allclose(back["x"], _table()["x"], atol=5e-4)
    meta = json.loads(metadata_path(tmp_path / "trees.csv").read_text())
    assert meta["@context"] == "http://www.w3.org/ns/csvw" and meta["url"] == "trees.csv"
    assert meta["prov:wasGeneratedBy"] == provenance
    assert meta["dc:creator"].startswith("canopy-kit ")
    cols = {c["name"]: c for c in meta["tableSchema"]["columns"]}
    assert list(cols) == list(_table().columns)
    assert cols["volume_alpha_m3"]["schema:unitText"] == "m³"
    assert cols["row"]["datatype"] == "integer" and cols["tree_id"]["datatype"] == "string"
    assert cols["lat"]["dc:description"] == "rounded to 8 decimals"
