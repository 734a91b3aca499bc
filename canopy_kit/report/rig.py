"""The report's sensor-rig section: which frame each sensor stamped, where its mount came
from, and whether the drive agrees with the IMU mount (``mapping.json``'s ``rig`` and
``extrinsics`` diagnostics; the check itself is ``checks.imu_mount_check``)."""

from __future__ import annotations

from typing import Any

import pandas as pd

from canopy_kit.report.html import ReportSection


def _pose(entry: dict[str, Any] | None) -> tuple[str, str]:
    if not entry:
        return "", ""

    def text(values: list[float], digits: int) -> str:  # no "-0.000"
        return ", ".join(f"{round(v, digits) + 0.0:.{digits}f}" for v in values)

    return text(entry["translation"], 3), text(entry["rpy_deg"], 2)


def rig_table(rig: dict[str, Any], inputs: dict[str, Any] | None = None) -> pd.DataFrame:
    """One row per sensor: the topic read (messages used of those met, time span), its frame,
    its mount on the vehicle and where the mount came from."""
    sources = rig.get("sources", {})
    mounts = rig.get("mounts_in_base", {})
    rows = [("LiDAR", rig.get("lidar_frame", ""), "lidar", sources.get("base", ""), "pointcloud")]
    if rig.get("imu_frame"):
        rows.append(("IMU", rig["imu_frame"], "imu", sources.get("imu", ""), "imu"))
    if rig.get("gnss_frame"):
        rows.append(("GNSS antenna", rig["gnss_frame"], "gnss", sources.get("gnss", ""), "gnss"))
    out = []
    for sensor, frame, key, source, role in rows:
        position, rpy = _pose(mounts.get(key))
        row = {"sensor": sensor}
        if inputs:
            row.update(_topic_columns((inputs or {}).get(role)))
        row.update(
            {
                "frame": frame,
                f"position in {rig.get('base_frame', 'base')} [m]": position,
                "roll, pitch, yaw [deg]": rpy if key != "gnss" else "",
                "source": source,
            }
        )
        out.append(row)
    return pd.DataFrame(out)


def _topic_columns(summary: dict[str, Any] | None) -> dict[str, str]:
    """Topic, messages used of those read, and the time span (bag clock) of the used ones."""
    if not summary:
        return {"topic": "not read", "messages used": "", "time span [s]": ""}
    span = ""
    if summary.get("first_stamp") is not None:
        span = f"{summary['first_stamp']:.3f} - {summary['last_stamp']:.3f} ({summary['duration_s']:.1f} s)"
    used = f"{summary['used']} of {summary['messages']}"
    if summary.get("trimmed"):
        used += f" ({summary['trimmed']} with extra bytes ignored)"
    return {"topic": summary["topic"], "messages used": used, "time span [s]": span}


def rig_section(mapping: dict[str, Any]) -> ReportSection | None:
    """The section for a run's mapping diagnostics (None when they hold no rig)."""
    rig = mapping.get("rig")
    if not rig:
        return None
    ext = mapping.get("extrinsics", {})
    text = (
        f"Trajectory reported for the frame '{rig.get('base_frame', '')}'. "
        f"Transforms read from {', '.join(rig.get('tf_topics') or []) or 'no tf topic'}"
        f"{' and a rig file' if 'rig file' in str(rig.get('sources')) else ''}."
    )
    est = ext.get("estimated")
    if est:
        verb = "Estimated" if ext.get("mode") == "calibrate" else "Checked against the drive"
        text += (
            f" {verb}: IMU mount roll/pitch/yaw {', '.join(f'{v:.2f}' for v in est['rpy_deg'])} deg "
            f"(1-sigma {', '.join(f'{v:.2f}' for v in est['sigma_deg'])} deg about the LiDAR's x, y, z)"
        )
        if "difference_deg" in ext:
            text += f", {ext['difference_deg']:.2f} deg from the given mount"
        text += "."
    if "lidar_tilt_from_gravity_deg" in ext:
        text += f" LiDAR tilted {ext['lidar_tilt_from_gravity_deg']:.1f} deg from the vertical at the start."
    if mapping.get("bag"):
        text = f"Read from {mapping['bag']}. " + text
    return ReportSection(
        "Sensor rig and topics", text=text, table=rig_table(rig, mapping.get("inputs"))
    )
