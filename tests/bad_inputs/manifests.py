"""Batch manifests whose ids are paths or clash, spreadsheets' CSVs, and a store cut short."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np


def toml_manifest(root: Path, *ids: str) -> Path:
    """One ``[[session]]`` per id (TOML basic strings), the bag never reached."""
    import json

    path = root / "sessions.toml"
    path.write_text(
        "".join(
            f'[[session]]\nid = {json.dumps(i)}\nbag = "b.mcap"\norchard = "o"\n'
            f"date = 2025-04-0{n + 1}\n"
            for n, i in enumerate(ids)
        )
    )
    return path


def csv_manifest(root: Path, body: bytes) -> Path:
    path = root / "sessions.csv"
    path.write_bytes(b"id,bag,orchard,date\n" + body)
    return path


def store_cut_short(root: Path, fraction: float = 0.4) -> Path:
    """A store with two sessions of 12 trees, copied up to ``fraction`` of its bytes."""
    from canopy_kit.core.geo import LocalFrame
    from canopy_kit.store import OrchardStore, SessionRecord

    frame = LocalFrame.at(37.281, -120.42)
    xy = np.array([[r * 6.0, i * 5.0] for r in range(2) for i in range(6)])
    lat, lon, _ = frame.to_wgs84(np.column_stack([xy, np.zeros(len(xy))]))
    full = root / "full.duckdb"
    with OrchardStore(full) as store:
        for month in (4, 6):
            trees = {
                "segment": np.arange(12),
                "label": [f"L{i}" for i in range(12)],
                "row": np.repeat([0, 1], 6),
                "lat": lat,
                "lon": lon,
                "n_points": 1000,
                "height_m": 3.0,
                "crown_diameter_m": 3.5,
                "volume_alpha_m3": 20.0 + month,
                "volume_flags": "",
            }
            import pandas as pd

            store.ingest(
                SessionRecord(f"v{month}", "block-a", dt.date(2025, month, 1), bag="b"),
                pd.DataFrame(trees),
            )
    data = full.read_bytes()
    cut = root / "orchard.duckdb"
    cut.write_bytes(data[: int(fraction * len(data))])
    full.unlink()
    return cut
