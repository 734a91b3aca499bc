"""What a bag or point-cloud file holds, as a plain dict (for ``canopy-kit info``)."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

from canopy_kit.errors import InputWarning
from canopy_kit.io.clouds import find_reader


def describe_path(path: str | Path) -> dict[str, Any]:
    """Facts about a file: bag topics, types, counts and time span; or cloud points,
    attributes with dtypes, bounds (from the points) and CRS. Keys ``reader`` and ``kind``
    name the plugin; ``warnings`` lists what the reader found wrong but could read past."""
    path = Path(path)
    reader = find_reader(path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", InputWarning)
        facts = dict(reader.describe(path))
    notes = list(facts.get("warnings", []))
    for w in caught:
        if issubclass(w.category, InputWarning):
            notes.append(str(w.message))
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    facts.setdefault("path", str(path))
    facts["reader"] = reader.name
    facts["kind"] = reader.kind
    facts["warnings"] = notes
    return facts
