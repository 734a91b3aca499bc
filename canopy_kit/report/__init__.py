"""Self-contained HTML reports: one file, every asset inlined, no network needed to open it."""

from canopy_kit.report.html import Check, ReportSection, render_report, write_report

__all__ = ["Check", "ReportSection", "render_report", "write_report"]
