"""Catalogue cases for faults inside a bag's messages (PointCloud2 headers, IMU samples,
clocks, topics), built by rewriting a short clean drive (:mod:`bad_inputs.messages`).

``bad_inputs.catalogue`` appends them to its ``CASES``: import them through it."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from bad_inputs import drives, messages
from bad_inputs.catalogue import MAP, Case

NAN_GYRO = (1e308, float("inf"), 0.0)  # the sample that aborted the process in KISS-ICP/Sophus


def _rewritten(edit: messages.Edit, **drive: object) -> Callable[[Path], tuple[list[str], str]]:
    """A 5 s drive (2000 points per scan) copied through ``edit``; ``canopy-kit map`` on it."""

    def build(root: Path) -> tuple[list[str], str]:
        drive.setdefault("duration", 5.0)
        drive.setdefault("points_per_scan", 2000)
        clean = drives.write_drive(root / "clean", **drive).path  # type: ignore[arg-type]
        bag = messages.rewrite_bag(clean, root / "drive", edit)
        return ["map", str(bag), "--out", str(root / "out"), *MAP], str(bag)

    return build


def few_malformed(topic: str = drives.POINTS_TOPIC) -> messages.Edit:
    """Scans 10, 20, 30 with an unknown datatype in ``x``; scans 15 and 25 with 48 extra bytes."""
    bad = messages.cloud_header(topic, fields=messages.field_changed("x", datatype=11))
    long = messages.padded_data(topic, 48)

    def edit(t: str, i: int, log_ns: int, msg: object) -> list | None:
        if t == topic and i in (10, 20, 30):
            return bad(t, 0, log_ns, msg)
        if t == topic and i in (15, 25):
            return long(t, 0, log_ns, msg)
        return None

    return edit


MESSAGE_CASES: tuple[Case, ...] = (
    Case(
        "bag-imu-nonfinite",
        "one IMU sample of 501 with angular velocity (1e308, inf, 0)",
        "sample dropped and counted; map as without it; warning naming the topic and message; flag "
        "imu_samples_dropped (before the fix: SOPHUS_ENSURE abort, exit 134, no error line)",
        0,
        _rewritten(messages.imu_sample(250, angular_velocity=NAN_GYRO)),
        ("'/imu/data': 1 of 501 IMU samples dropped", "angular velocity not finite", "message 250"),
        ("imu_samples_dropped",),
    ),
    Case(
        "bag-imu-mostly-nonfinite",
        "every third IMU sample has a NaN acceleration",
        "error naming the topic, the share and the first bad message (before: SOPHUS_ENSURE abort, "
        "exit 134)",
        2,
        _rewritten(messages.imu_sample(-3, linear_acceleration=(float("nan"), 0.0, 9.8))),
        (
            "topic '/imu/data'",
            "IMU samples unusable",
            "linear acceleration not finite",
            "message 0",
        ),
    ),
    Case(
        "bag-imu-accel-zero",
        "every IMU sample's linear acceleration is (0, 0, 0) (a dead accelerometer)",
        "error naming the topic and the way out (before: a NaN attitude, SOPHUS_ENSURE "
        "abort, exit 134)",
        2,
        _rewritten(messages.imu_sample(-1, linear_acceleration=(0.0, 0.0, 0.0))),
        ("topic '/imu/data'", "no direction of gravity", "mapping.use_imu=false"),
    ),
    Case(
        "bag-gnss-nonfinite",
        "three GNSS fixes that claim a fix: latitude NaN, altitude +Inf, latitude 95 deg",
        "the three dropped and counted; georeferenced map; warning naming the "
        "topic and the first; flag gnss_fixes_dropped",
        0,
        _rewritten(
            messages.chain(
                messages.gnss_fix((5,), latitude=float("nan")),
                messages.gnss_fix((10,), altitude=float("inf")),
                messages.gnss_fix((15,), latitude=95.0),
            )
        ),
        ("'/gps/fix': 3 of 26 fixes had a non-finite or impossible latitude", "first: fix 5"),
        ("gnss_fixes_dropped",),
        ("not_georeferenced",),
    ),
    Case(
        "bag-pc2-half-width",
        "PointCloud2 width (and row_step) halved on every scan: the data holds twice the points",
        "error naming the topic, the header fields and the first message "
        "(before the fix: half of every sweep mapped, 5 trees instead of 3, no warning)",
        2,
        _rewritten(messages.cloud_header(width=lambda w: w // 2, row_step=lambda r: r // 2)),
        (
            "topic '/points'",
            "hold more data than their header describes",
            "message 0",
            "width x height x point_step",
        ),
    ),
    Case(
        "bag-pc2-double-width",
        "PointCloud2 width doubled on every scan: the data holds half the points",
        "error naming the topic, the fields and the first message",
        2,
        _rewritten(messages.cloud_header(width=lambda w: 2 * w, row_step=lambda r: 2 * r)),
        ("topic '/points'", "scans unusable", "message 0", "too few for"),
    ),
    Case(
        "bag-pc2-point-step-small",
        "PointCloud2 point_step 8 bytes shorter than its fields",
        "error naming the field that reaches past point_step",
        2,
        _rewritten(messages.cloud_header(point_step=lambda s: s - 8)),
        ("topic '/points'", "beyond point_step", "message 0"),
    ),
    Case(
        "bag-pc2-field-offset",
        "PointCloud2 field 'intensity' at offset 200 (point_step 20)",
        "error naming the field, its offset and point_step",
        2,
        _rewritten(messages.cloud_header(fields=messages.field_changed("intensity", offset=200))),
        ("topic '/points'", "field 'intensity' (offset 200", "beyond point_step 20"),
    ),
    Case(
        "bag-pc2-unknown-datatype",
        "PointCloud2 field 'x' of datatype 11 (PointField knows 1-8)",
        "error naming the field and the datatype",
        2,
        _rewritten(messages.cloud_header(fields=messages.field_changed("x", datatype=11))),
        ("topic '/points'", "field 'x' has unknown datatype 11", "message 0"),
    ),
    Case(
        "bag-pc2-few-malformed",
        "3 of 50 scans with an unknown datatype, 2 with 48 bytes more "
        "data than their header describes",
        "the 3 dropped and counted, the extra bytes ignored; "
        "warnings naming topic, field and message; flags scans_malformed, scan_bytes_ignored (before: "
        "exit 2 at the first malformed scan)",
        0,
        _rewritten(few_malformed()),
        (
            "3 of 50 scans dropped",
            "message 10: field 'x' has unknown datatype 11",
            "2 of 50 scans hold more data",
            "message 15",
        ),
        ("scans_malformed", "scan_bytes_ignored"),
    ),
    Case(
        "bag-clock-jump-back",
        "every sensor's header stamps jump back 15 s at 2.5 s into the drive",
        "error naming the topic, the jump and the message (before the fix: flagged, but the IMU of two "
        "stretches sorted into one: 6 trees instead of 3)",
        2,
        _rewritten(messages.clock_jump(2.5, -15.0)),
        ("header stamps jump back", "the sensor clock jumped back"),
    ),
    Case(
        "bag-two-pointclouds",
        "two PointCloud2 topics with as many messages: '/points' and a thinned copy '/points_raw'",
        "map of '/points'; warning naming both and the one read; the "
        'topic written to the config saved with the map (before: no warning, pointcloud_topic = "")',
        0,
        _rewritten(messages.second_cloud()),
        ("2 sensor_msgs/msg/PointCloud2 topics", "read '/points'"),
    ),
)
