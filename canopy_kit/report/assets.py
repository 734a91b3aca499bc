"""The JavaScript the report inlines: vendored plotly.js (see scripts/vendor_js.py) and its own."""

from __future__ import annotations

import json
from functools import cache
from importlib.resources import files
from typing import Any


@cache
def plotly_js() -> str:
    """plotly.js-dist-min as vendored into ``canopy_kit/report/vendor`` (safe to inline)."""
    text = (
        files("canopy_kit.report").joinpath("vendor", "plotly.min.js").read_text(encoding="utf-8")
    )
    return text.replace("</script", "<\\/script")


def vendored() -> dict[str, Any]:
    """What was vendored: package -> version, integrity hash, tarball and files."""
    return json.loads(files("canopy_kit.report").joinpath("vendor", "VENDORED.json").read_text())


@cache
def page_script() -> str:
    """The report's own script: table search and sort, map, histogram, drill-down, downloads."""
    return files("canopy_kit.report").joinpath("templates", "report.js").read_text(encoding="utf-8")
