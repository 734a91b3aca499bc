"""What a bag or point-cloud file holds, as a plain dict (for ``canopy-kit info``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from canopy_kit.io.clouds import find_reader


def describe_path(path: str | Path) -> dict[str, Any]:
    """Facts about a file: bag topics, types, counts and time span; or cloud points,
    attributes with dtypes, bounds and CRS. Keys ``reader`` and ``kind`` name the plugin."""
    path = Path(path)
    reader = find_reader(path)
    facts = dict(reader.describe(path))
    facts.setdefault("path", str(path))
    facts["reader"] = reader.name
    facts["kind"] = reader.kind
    return facts
