"""Open a report in headless Chromium with the network blocked and read back what rendered."""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path

from canopy_kit.errors import ProcessingError

CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--no-first-run",
    "--disable-sync",
    "--disable-quic",
]


@dataclass
class RenderedPage:
    """What the browser showed: table rows, images that decoded, blocked requests, errors."""

    title: str
    tree_rows: int
    images_loaded: int
    images_broken: int
    check_rows: int
    blocked_requests: list[str] = field(default_factory=list)
    console_errors: list[str] = field(default_factory=list)
    sorted_first_cells: list[str] = field(default_factory=list)
    headline: str = ""  # the verdict banner's title, as rendered


def find_chromium() -> str:
    """Path of the system Chromium (Debian's ``chromium``)."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    raise ProcessingError("no Chromium found; install Debian's chromium (make setup does)")


def render_page(
    path: str | Path, screenshot: str | Path | None = None, sort_column: int | None = None
) -> RenderedPage:
    """Load ``path`` offline in headless Chromium; optionally click a column header to sort."""
    from playwright.sync_api import sync_playwright

    url = Path(path).resolve().as_uri()
    blocked: list[str] = []
    errors: list[str] = []
    # Playwright gives every launch a fresh, temporary profile (user data dir).
    with sync_playwright() as pw:
        browser = pw.chromium.launch(
            executable_path=find_chromium(), args=CHROMIUM_ARGS, headless=True
        )
        page = browser.new_page(viewport={"width": 1400, "height": 1000})

        def route(r):
            if r.request.url.startswith(("file:", "data:")):
                return r.continue_()
            blocked.append(r.request.url)
            return r.abort()

        page.route("**/*", route)
        page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(url, wait_until="load")
        tree_rows = page.locator("#trees tbody tr").count()
        check_rows = page.locator("#checks-table tbody tr").count()
        loaded = page.evaluate(
            "Array.from(document.images).filter(i => i.complete && i.naturalWidth > 0).length"
        )
        broken = page.evaluate(
            "Array.from(document.images).filter(i => !(i.complete && i.naturalWidth > 0)).length"
        )
        first_cells: list[str] = []
        if sort_column is not None and tree_rows:
            page.locator(f"#trees th[data-col='{sort_column}']").click()
            first_cells = page.eval_on_selector_all(
                f"#trees tbody tr td:nth-child({sort_column + 1})",
                "els => els.map(e => e.textContent)",
            )
        if screenshot is not None:
            Path(screenshot).parent.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(screenshot), full_page=True)
        title = page.title()
        banner = page.locator("#verdict h2")
        headline = banner.inner_text() if banner.count() else ""
        browser.close()
    return RenderedPage(
        title, tree_rows, loaded, broken, check_rows, blocked, errors, first_cells, headline
    )
