"""The reader's per-topic log: IMU plausibility, the drop thresholds, the clock-jump rule and
the stitching of chunk logs (hand-computed values)."""

from __future__ import annotations

import math

import pytest

from canopy_kit.errors import InputError
from canopy_kit.io.message_log import MessageLog, TopicLog, imu_sample_fault, merged

GRAVITY = (0.0, 0.0, 9.81)


@pytest.mark.parametrize(
    ("gyro", "acc", "fault"),
    [
        ((0.01, -0.02, 0.3), GRAVITY, None),
        ((49.0, 0.0, 0.0), (0.0, 0.0, 499.0), None),
        ((1e308, math.inf, 0.0), GRAVITY, "angular velocity not finite"),
        ((1e308, 1e308, 0.0), GRAVITY, "angular velocity above 50 rad/s"),  # its square overflows
        ((30.0, 30.0, 30.0), GRAVITY, "angular velocity above 50 rad/s"),  # |w| = 52
        ((0.0, 0.0, 0.0), (math.nan, 0.0, 9.8), "linear acceleration not finite"),
        ((0.0, 0.0, 0.0), (300.0, 300.0, 300.0), "linear acceleration above 500 m/s²"),  # |a| = 520
    ],
)
def test_imu_sample_fault(gyro: tuple, acc: tuple, fault: str | None) -> None:
    assert imu_sample_fault(gyro, acc) == fault


def test_drops_up_to_a_fifth_are_warned_of_and_more_are_an_error() -> None:
    log = TopicLog("/imu", "IMU samples", "bag")
    for i in range(10):
        if i in (3, 7):
            log.drop(i, "angular velocity not finite", f"message {i}: nan")
        else:
            log.use(i, 100.0 + i)
    log.check()  # 2 of 10: 20 %, not more
    assert log.warnings() == [
        "bag: topic '/imu': 2 of 10 IMU samples dropped (2 angular velocity not "
        "finite); first: message 3: nan"
    ]
    log.drop(10, "linear acceleration not finite", "message 10: nan")  # 3 of 11
    with pytest.raises(
        InputError,
        match=r"bag: topic '/imu': 3 of 11 IMU samples unusable \(more than "
        r"20 %: 2 angular velocity not finite, 1 linear acceleration not "
        r"finite\); first: message 3: nan",
    ):
        log.check()
    summary = log.summary()
    assert (summary["used"], summary["dropped"], summary["first_stamp"], summary["last_stamp"]) == (
        8,
        3,
        100.0,
        109.0,
    )


def test_mostly_bad_first_messages_stop_at_once() -> None:
    log = TopicLog("/points", "scans", "bag")
    for i in range(24):
        log.use(i, float(i))
    with pytest.raises(InputError, match="26 of 50 scans unusable"):
        for i in range(24, 50):
            log.drop(i, "malformed", f"message {i}: bad")


def test_extra_bytes_are_trimmed_and_a_lying_header_on_most_scans_is_an_error() -> None:
    log = TopicLog("/points", "scans", "bag")
    for i in range(10):
        log.use(i, float(i))
    log.trim(2, 8, 40_000, "message 2: 8 more")  # tail padding: trimmed, does not undercount
    log.trim(4, 20_000, 20_000, "message 4: twice")  # half the points unclaimed
    log.check()
    assert log.undercounted == 1 and "(20008 bytes ignored)" in log.warnings()[0]
    for i in (5, 6):
        log.trim(i, 20_000, 20_000, "")
    with pytest.raises(
        InputError, match="3 of 10 scans hold more data than their header describes"
    ):
        log.check()


def test_a_late_or_repeated_stamp_passes_and_a_clock_that_stays_behind_is_an_error() -> None:
    log = TopicLog("/points", "scans", "bag")
    ns = 1_000_000_000
    log.watch_clock(0, 10.0, 0)
    log.watch_clock(1, 10.1, ns // 10)
    log.watch_clock(2, 9.75, 2 * ns // 10)  # one scan 0.35 s late
    log.watch_clock(3, 10.2, 3 * ns // 10)
    log.watch_clock(4, 10.2, 4 * ns // 10)  # repeated
    with pytest.raises(InputError) as err:  # 15 s back, logged 0.1 s apart from 1.5 s on
        for k in range(5, 40):
            log.watch_clock(k, 10.2 + 0.1 * (k - 4) - 15.0, (k + 10) * ns // 10)
    assert k == 16  # the first message behind for more than 1 s of recording (2.6 - 1.5 s)
    assert "header stamps jump back 14.900 s at message 5" in str(err.value)
    assert "stay behind for 12 messages over 1.1 s of recording" in str(err.value)


def test_a_second_pass_over_the_bag_is_not_a_clock_jump() -> None:
    """Calibration reads the bag twice through one session: the second pass starts again at
    message 0, whose stamp is behind the first pass's last (measured: exit 2 on a tower
    session before this was told apart)."""
    log = TopicLog("/imu/data", "IMU samples", "bag")
    ns = 1_000_000_000
    for _ in range(2):
        for k in range(300):
            log.watch_clock(k, 100.0 + 0.005 * k, k * ns // 200)
    with pytest.raises(InputError, match="jump back"):  # a real jump within the second pass
        for k in range(300, 600):
            log.watch_clock(k, 80.0 + 0.005 * k, k * ns // 200)


def test_chunk_logs_restricted_to_their_own_scans_merge_into_the_whole() -> None:
    parts = []
    for first, last, bad in ((0, 60, {10}), (40, 100, {50, 90})):  # chunk 2 re-reads 40-59
        log = TopicLog("/points", "scans", "bag")
        for i in range(first, last):
            log.drop(i, "malformed", f"message {i}") if i in bad else log.use(i, float(i))
        parts.append(log)
    whole = merged([parts[0].restricted(0, 50), parts[1].restricted(50, math.inf)])
    assert (whole.seen, whole.used, sorted(whole.dropped)) == (100, 97, [10, 50, 90])
    assert whole.index_range == (0, 100)
    mlog = MessageLog("bag")
    mlog.topics["/points"] = whole
    assert (
        mlog.flags() == ["scans_malformed"]
        and mlog.summary({"pointcloud": "/points"})["pointcloud"]["dropped"] == 3
    )


def test_a_second_pass_counts_each_message_once() -> None:
    """A calibrated run reads the bag twice through one log: 25 of 100 scans dropped is
    25 %, an error, however many passes read them (counted twice it was 25 of 175)."""
    log = TopicLog("/points", "scans", "drive.bag")
    for _ in range(2):
        for i in range(100):
            if i % 4 == 0:
                log.drop(i, "truncated", f"scan {i}: truncated")
            else:
                log.use(i, float(i))
    assert (log.seen, log.used, len(log.dropped)) == (100, 75, 25)
    with pytest.raises(InputError, match="25 of 100 scans unusable"):
        log.check()
