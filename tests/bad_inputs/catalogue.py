"""The bad-input catalogue: every case, the input it builds and the behaviour a user gets.

Each case builds its input under a folder and names the ``canopy-kit`` command a user would
run on it. The expected behaviour is one of:

- exit 2 (bad input) or 3 (processing failed) with a one-line ``error:`` message naming the
  file, topic, field or parameter and what is wrong, and no traceback;
- exit 0 with a result, warnings saying what was wrong, and quality flags in the output
  (``mapping.json`` → ``diagnostics.quality_flags``; ``metrics.json`` → ``mapping`` for a run).

docs/RELIABILITY.md lists the same cases (a test keeps the two in step).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bad_inputs import clouds, corrupt, drives, drone, manifests, presets

MAP = ("--no-plots",)


@dataclass(frozen=True)
class Case:
    """One catalogue entry."""

    id: str
    input: str  # what is wrong with the input
    behaviour: str  # what the user gets
    exit_code: int
    build: Callable[
        [Path], tuple[list[str], str]
    ]  # -> CLI arguments, the name the message must hold
    expect: tuple[
        str, ...
    ] = ()  # fragments of the error line (exit 2/3) or of the warnings (exit 0)
    flags: tuple[str, ...] = ()  # quality flags the result must carry (exit 0)
    absent_flags: tuple[str, ...] = ()  # quality flags it must not carry

    @property
    def category(self) -> str:
        return self.id.split("-")[0]


def _map(bag: Path, root: Path, *extra: str) -> list[str]:
    return ["map", str(bag), "--out", str(root / "out"), *MAP, *extra]


def _drive(root: Path, fmt: str = "ros2-mcap", **kw: object) -> Path:
    kw.setdefault("duration", 5.0)
    kw.setdefault("points_per_scan", 2000)
    return drives.write_drive(root / "drive", fmt, **kw).path  # type: ignore[arg-type]


_SHARED: dict[str, Path] = {}


def _valid_bag(root: Path) -> Path:
    """A short clean drive, written once and shared by the cases whose fault lies elsewhere."""
    if "bag" not in _SHARED or not _SHARED["bag"].exists():
        _SHARED["bag"] = _drive(root, duration=2.0)
    return _SHARED["bag"]


def _cut(fmt: str, seed: int) -> Callable[[Path], tuple[list[str], str]]:
    def build(root: Path) -> tuple[list[str], str]:
        bag = _drive(root, fmt, duration=6.0)
        fraction = float(np.random.default_rng(seed).uniform(0.45, 0.85))
        corrupt.cut_bag(bag, fraction)
        return _map(bag, root), str(bag)

    return build


def _corrupt_bytes(fmt: str, seed: int) -> Callable[[Path], tuple[list[str], str]]:
    def build(root: Path) -> tuple[list[str], str]:
        bag = corrupted_drive(root, fmt, seed)
        return _map(bag, root), str(bag)

    return build


def corrupted_drive(root: Path, fmt: str, seed: int) -> Path:
    """A 5 s drive with 16 random bytes overwritten at up to 4 seeded offsets inside its
    messages (10-90 % of the storage file): a bad sector or a flaky card."""
    bag = _drive(root, fmt)
    storage = corrupt.storage_file(bag)
    size = storage.stat().st_size
    rng = np.random.default_rng(seed)
    offsets = corrupt.random_offsets(size, 4, rng, start=size // 10)
    corrupt.overwrite(storage, offsets[offsets < size * 0.9], rng, 16)
    return bag


def _cut_at_start(root: Path) -> tuple[list[str], str]:
    bag = _drive(root, "ros1", duration=2.0)
    corrupt.cut(bag, 64)
    return _map(bag, root), str(bag)


def _damaged_index(root: Path) -> tuple[list[str], str]:
    bag = _drive(root, "ros1")
    size = bag.stat().st_size
    corrupt.overwrite(bag, np.array([size - 200]), np.random.default_rng(3), 64)
    return _map(bag, root), str(bag)


def _damaged_summary(root: Path) -> tuple[list[str], str]:
    bag = _drive(root, "ros2-mcap")
    storage = corrupt.storage_file(bag)
    data = bytearray(storage.read_bytes())
    data[-8:] = b"\0" * 8  # the closing magic of the footer
    storage.write_bytes(bytes(data))
    return _map(bag, root), str(bag)


def _no_points(root: Path) -> tuple[list[str], str]:
    bag = drives.write_without_points(root / "drive")
    return _map(bag, root), str(bag)


def _named_topic(topic: str) -> Callable[[Path], tuple[list[str], str]]:
    def build(root: Path) -> tuple[list[str], str]:
        bag = _valid_bag(root)
        return _map(bag, root, "--set", f"pointcloud_topic={topic!r}".replace("'", '"')), topic

    return build


def _wrong_payload(root: Path) -> tuple[list[str], str]:
    bag = drives.write_wrong_payload(root / "drive", "ros1")
    return _map(bag, root), str(bag)


def _faulty(fault: drives.Fault, **kw: object) -> Callable[[Path], tuple[list[str], str]]:
    def build(root: Path) -> tuple[list[str], str]:
        bag = _drive(root, fault=fault, **kw)
        return _map(bag, root), str(bag)

    return build


def _sensors(**kw: object) -> Callable[[Path], tuple[list[str], str]]:
    def build(root: Path) -> tuple[list[str], str]:
        bag = _drive(root, **kw)
        return _map(bag, root), str(bag)

    return build


def _frames(*extra: str, rig_text: str | None = None) -> Callable[[Path], tuple[list[str], str]]:
    """The IMU stamps its own frame and nothing in the bag relates it to the LiDAR's."""

    def build(root: Path) -> tuple[list[str], str]:
        bag = _drive(root, imu_frame="imu_link")
        if rig_text is None:
            return _map(bag, root, *extra), str(bag)
        rig = root / "rig.toml"
        rig.write_text(rig_text)
        return _map(bag, root, "--rig", str(rig)), str(rig)

    return build


def _missing_bag(root: Path) -> tuple[list[str], str]:
    bag = root / "nowhere.bag"
    return ["run", str(bag), "--out", str(root / "out")], str(bag)


def _empty_bag(root: Path) -> tuple[list[str], str]:
    bag = root / "empty.bag"
    bag.touch()
    return _map(bag, root), str(bag)


def _text_bag(root: Path) -> tuple[list[str], str]:
    bag = root / "notes.bag"
    bag.write_text("rosbag record -a\n")
    return _map(bag, root), str(bag)


def _las(**kw: object) -> Callable[[Path], tuple[list[str], str]]:
    def build(root: Path) -> tuple[list[str], str]:
        path = clouds.write_raw_las(root / "tree.las", **kw)  # type: ignore[arg-type]
        return ["volume", str(path)], str(path)

    return build


def _las_truncated(root: Path) -> tuple[list[str], str]:
    path = clouds.write_truncated_laz(root / "tree.laz")
    return ["volume", str(path)], str(path)


def _las_garbage(root: Path) -> tuple[list[str], str]:
    path = root / "tree.las"
    path.write_bytes(np.random.default_rng(4).integers(0, 256, 3000, dtype=np.uint8).tobytes())
    return ["volume", str(path)], str(path)


def _cloud(
    make: Callable[[Path], Path], name: str, *command: str
) -> Callable[[Path], tuple[list[str], str]]:
    """A point-cloud file ``name`` made by ``make``, given to ``canopy-kit COMMAND FILE``."""

    def build(root: Path) -> tuple[list[str], str]:
        path = make(root / name)
        return [command[0], str(path), *command[1:]], str(path)

    return build


def _drone(
    make: Callable[[Path], Path], name_folder: bool = False
) -> Callable[[Path], tuple[list[str], str]]:
    def build(root: Path) -> tuple[list[str], str]:
        folder = root / "photos"
        bad = make(folder)
        return ["ground-truth", str(folder), "--out", str(root / "out")], str(
            folder if name_folder else bad
        )

    return build


def _drone_in_run(root: Path) -> tuple[list[str], str]:
    bag = _valid_bag(root)
    folder = root / "photos"
    bad = drone.without_gps(folder)
    return ["run", str(bag), "--out", str(root / "out"), "--drone-images", str(folder)], str(bad)


def _batch(make: Callable[[Path], Path]) -> Callable[[Path], tuple[list[str], str]]:
    def build(root: Path) -> tuple[list[str], str]:
        manifest = make(root)
        return ["batch", str(manifest), "--out", str(root / "out")], str(manifest)

    return build


def _store_cut(root: Path) -> tuple[list[str], str]:
    store = manifests.store_cut_short(root)
    return ["store", "growth", str(store)], str(store)


def _preset(case: str, named: str | None = None) -> Callable[[Path], tuple[list[str], str]]:
    def build(root: Path) -> tuple[list[str], str]:
        bag = _valid_bag(root)
        path = presets.write_preset(root, case)
        return ["run", str(bag), "--out", str(root / "out"), "--preset", str(path)], named or str(
            path
        )

    return build


def _override(setting: str, named: str) -> Callable[[Path], tuple[list[str], str]]:
    def build(root: Path) -> tuple[list[str], str]:
        bag = _valid_bag(root)
        return ["run", str(bag), "--out", str(root / "out"), "--set", setting], named

    return build


RECOVERED = "damaged or cut short"
CASES: tuple[Case, ...] = (
    # -- bags: damaged files -------------------------------------------------------------------
    Case(
        "bag-cut-ros1",
        "ROS1 bag cut at a random byte offset (45-85 %): no index",
        "map of the drive up to the cut; warning with the messages recovered; flag bag_recovered",
        0,
        _cut("ros1", 11),
        (RECOVERED,),
        ("bag_recovered",),
    ),
    Case(
        "bag-cut-sqlite3",
        "ROS2 sqlite3 bag whose .db3 is cut at a random byte offset",
        "map up to the cut (rows before the first missing page); warning; flag bag_recovered",
        0,
        _cut("ros2-sqlite3", 12),
        (RECOVERED,),
        ("bag_recovered",),
    ),
    Case(
        "bag-cut-mcap",
        "ROS2 MCAP bag cut at a random byte offset: no summary, no footer",
        "map up to the cut (complete records, and the start of a cut chunk); warning; flag "
        "bag_recovered",
        0,
        _cut("ros2-mcap", 13),
        (RECOVERED,),
        ("bag_recovered",),
    ),
    Case(
        "bag-corrupt-bytes-ros1",
        "ROS1 bag with 16 random bytes overwritten at seeded random offsets in its messages",
        "map; the points whose per-point time the damage scrambled "
        "dropped with a warning (before the fix: one such time stretched its sweep and moved the "
        "trajectory by 2.6 m, silently); flag point_times_dropped",
        0,
        _corrupt_bytes("ros1", 2),
        ("per-point times more than 1 s",),
        ("point_times_dropped",),
    ),
    Case(
        "bag-corrupt-bytes-sqlite3",
        "ROS2 sqlite3 bag with random bytes overwritten in its rows",
        "map; scrambled points dropped with a warning; flag point_times_dropped",
        0,
        _corrupt_bytes("ros2-sqlite3", 1),
        ("per-point times more than 1 s",),
        ("point_times_dropped",),
    ),
    Case(
        "bag-corrupt-bytes-mcap",
        "ROS2 MCAP bag with random bytes overwritten in its chunks",
        "map; scrambled points dropped with a warning; flag point_times_dropped",
        0,
        _corrupt_bytes("ros2-mcap", 2),
        ("per-point times more than 1 s",),
        ("point_times_dropped",),
    ),
    Case(
        "bag-cut-at-start",
        "ROS1 bag cut 64 bytes in, before any message",
        "error: cannot open bag, nothing recoverable",
        2,
        _cut_at_start,
        ("cannot open bag", "no complete message"),
    ),
    Case(
        "bag-damaged-index",
        "ROS1 bag with bytes overwritten in its index (end of file)",
        "every message read in file order; warning; flag bag_recovered",
        0,
        _damaged_index,
        (RECOVERED,),
        ("bag_recovered",),
    ),
    Case(
        "bag-damaged-footer",
        "MCAP bag whose footer magic is overwritten",
        "every message read in file order; warning; flag bag_recovered",
        0,
        _damaged_summary,
        (RECOVERED,),
        ("bag_recovered",),
    ),
    Case(
        "bag-missing",
        "bag path that does not exist",
        "error naming the path",
        2,
        _missing_bag,
        ("does not exist",),
    ),
    Case("bag-empty-file", "0-byte .bag file", "error: file is empty", 2, _empty_bag, ("empty",)),
    Case(
        "bag-not-a-bag",
        "text file named .bag",
        "error: cannot open bag",
        2,
        _text_bag,
        ("cannot open bag",),
    ),
    # -- bags: topics and messages ---------------------------------------------------------------
    Case(
        "bag-no-pointcloud",
        "bag with IMU and GNSS but no PointCloud2 topic",
        "error naming the missing message type",
        2,
        _no_points,
        ("no sensor_msgs/msg/PointCloud2 topic",),
    ),
    Case(
        "bag-topic-missing",
        "configured point-cloud topic not in the bag",
        "error naming the topic and listing the bag's topics",
        2,
        _named_topic("/velodyne_points"),
        ("no topic '/velodyne_points'", "topics: "),
    ),
    Case(
        "bag-topic-wrong-type",
        "configured point-cloud topic carries Imu messages",
        "error naming the topic, its type and the expected type",
        2,
        _named_topic("/imu/data"),
        ("carries sensor_msgs/msg/Imu, expected sensor_msgs/msg/PointCloud2",),
    ),
    Case(
        "bag-payload-wrong-type",
        "topic declared PointCloud2 whose messages are Imu bytes",
        "error naming the topic, the message time and the decoding failure",
        2,
        _wrong_payload,
        ("'/points'", "cannot decode a sensor_msgs/msg/PointCloud2 message"),
    ),
    Case(
        "bag-empty-scans-some",
        "three scans with zero points",
        "map without them; warning; flag scans_skipped",
        0,
        _faulty(drives.emptied([20, 21, 40])),
        ("3 scans had fewer than 500 points",),
        ("scans_skipped",),
    ),
    Case(
        "bag-empty-scans-all",
        "every scan has zero points",
        "error naming the topic and scans and the setting min_points_per_scan",
        2,
        _faulty(drives.emptied(), duration=2.0),
        ("only 0 valid points", "min_points_per_scan"),
    ),
    Case(
        "bag-nonfinite-points",
        "NaN and Inf coordinates in 1 point of 7, one scan all NaN",
        "non-finite points dropped, the all-NaN scan skipped; finite map; flag scans_skipped",
        0,
        _faulty(drives.nonfinite(all_nan_sweep=30)),
        ("1 scans had fewer than 500 points",),
        ("scans_skipped",),
    ),
    # -- bags: time ------------------------------------------------------------------------------
    Case(
        "bag-repeated-stamps",
        "two scans published twice with the same header stamp",
        "repeats skipped; warning; flag scans_out_of_order (before the fix: runaway poses, "
        "memory exhausted)",
        0,
        _faulty(drives.repeated(30, 31)),
        ("2 scans stamped at or before",),
        ("scans_out_of_order",),
    ),
    Case(
        "bag-backwards-stamp",
        "one scan stamped 0.35 s in the past (sensor clock jump)",
        "that scan skipped; warning; flag scans_out_of_order",
        0,
        _faulty(drives.stamped_back(30, 0.35)),
        ("1 scans stamped at or before",),
        ("scans_out_of_order",),
    ),
    Case(
        "bag-dropout",
        "LiDAR silent for 4 s while the robot drives (IMU and GNSS go on)",
        "map with a hole; warning with the gap; flag scan_gaps",
        0,
        _faulty(drives.dropout(25, 65), duration=9.0),
        ("sensor dropout", "no scan for 4.1 s"),
        ("scan_gaps",),
    ),
    Case(
        "bag-standing-still",
        "the robot never moves",
        "map of what one spot sees, not georeferenced (no heading from GNSS); warnings; flags "
        "standing_still, not_georeferenced",
        0,
        _sensors(speed=0.0, duration=4.0),
        ("the robot moved at most", "too little for a heading from GNSS"),
        ("standing_still", "not_georeferenced"),
    ),
    # -- bags: sensors ---------------------------------------------------------------------------
    Case(
        "bag-imu-without-gnss",
        "IMU but no GNSS topic",
        "map in a local frame; warning; flag not_georeferenced",
        0,
        _sensors(gnss=False),
        ("no GNSS topic",),
        ("not_georeferenced",),
        ("no_imu",),
    ),
    Case(
        "bag-gnss-without-imu",
        "GNSS but no IMU topic",
        "georeferenced map, LiDAR-only odometry; warning; flag no_imu",
        0,
        _sensors(imu=False),
        ("no IMU topic",),
        ("no_imu",),
        ("not_georeferenced",),
    ),
    Case(
        "bag-frames-unrelated",
        "the LiDAR stamps 'lidar', the IMU 'imu_link'; no /tf_static, no rig file",
        "error naming both frames and topics and the ways out (--rig, --calibrate-extrinsics, "
        "--assume-identity-extrinsics)",
        2,
        _frames(),
        (
            "'lidar'",
            "'imu_link'",
            "--rig FILE",
            "--calibrate-extrinsics",
            "--assume-identity-extrinsics",
        ),
    ),
    Case(
        "bag-frames-assumed-identity",
        "the same bag with --assume-identity-extrinsics",
        "map as if the frames were one; warning naming both",
        0,
        _frames("--assume-identity-extrinsics"),
        ("'imu_link' differ and nothing relates them",),
    ),
    Case(
        "bag-rig-file-bad",
        "--rig file whose IMU mount has two angles (rpy_deg = [180, 0])",
        "error naming the file and the key",
        2,
        _frames(rig_text='[frames.imu_link]\nparent = "lidar"\nrpy_deg = [180, 0]\n'),
        ("frames.imu_link.rpy_deg", "a list of 3 numbers"),
    ),
    # -- point clouds ----------------------------------------------------------------------------
    Case(
        "las-zero-points",
        "LAS file with a header and no points",
        "error: no points",
        2,
        _las(n_points=0),
        ("has no points",),
    ),
    Case(
        "las-scale-zero",
        "LAS header scale factors 0 (every point on the offset)",
        "error naming the header scale",
        2,
        _las(scale=0.0),
        ("scale factors", "corrupt"),
    ),
    Case(
        "las-scale-negative",
        "LAS header scale factors -0.001 (a mirrored cloud)",
        "error naming the header scale",
        2,
        _las(scale=-0.001),
        ("scale factors",),
    ),
    Case(
        "las-scale-nan",
        "LAS header scale factors NaN (every coordinate NaN)",
        "error naming the header scale",
        2,
        _las(scale=float("nan")),
        ("scale factors",),
    ),
    Case(
        "las-offset-inf",
        "LAS header offsets infinite",
        "error naming the header offsets",
        2,
        _las(offset=float("inf")),
        ("offsets",),
    ),
    Case(
        "las-truncated",
        "LAZ file cut at 60 %",
        "error: corrupt or truncated",
        2,
        _las_truncated,
        ("corrupt or truncated",),
    ),
    Case(
        "las-garbage",
        "random bytes named .las",
        "error: not a LAS/LAZ file",
        2,
        _las_garbage,
        ("not a LAS/LAZ file",),
    ),
    Case(
        "las-vlr-bomb",
        "3 KB: a LAS header claiming 4,000,000,000 VLRs, then random bytes",
        "error naming the header field, at once (before the fix: 131 s and 5.6 GB, then "
        "MemoryError)",
        2,
        _cloud(clouds.write_las_vlr_bomb, "bomb.las", "info"),
        ("'number of variable length records'",),
    ),
    Case(
        "las-count-claimed-1e8",
        "LAS of 20,000 points whose header claims 100,000,000",
        "the 20,000 points, warning 'N of M points' (before the fix: 3.5 GB, no warning)",
        0,
        _cloud(
            lambda p: clouds.write_las_claiming(p, 20_000, point_count=100_000_000),
            "tree.las",
            "volume",
            "--method",
            "convex_hull",
        ),
        ("only 20000 of 100000000 points are in the file",),
    ),
    Case(
        "las-record-length-65535",
        "LAS header point record length 65535 (36 written)",
        "error naming the header field (before the fix: 2.4 GB, then an error)",
        2,
        _cloud(
            lambda p: clouds.write_las_claiming(p, 20_000, record_length=65535),
            "tree.las",
            "volume",
        ),
        ("'point data record length' is 65535",),
    ),
    Case(
        "las-scale-tiny",
        "LAS header scale factors 1e-300",
        "error naming the header scale (before the fix: MemoryError 21.1 GiB, exit 3)",
        2,
        _las(scale=1e-300),
        ("scale factors", "1e-09"),
    ),
    Case(
        "las-cut-at-record",
        "LAS of 37,657 points cut exactly after record 20,000",
        "flagged result: the 20,000 complete records and a warning 'N of M points' (before the "
        "fix: silently 20,000 points)",
        0,
        _cloud(
            lambda p: clouds.write_las_cut(p, 37_657, 20_000),
            "cut.las",
            "volume",
            "--method",
            "convex_hull",
        ),
        ("only 20000 of 37657 points are in the file",),
    ),
    Case(
        "las-zero-header-bounds",
        "LAS whose header min/max are all 0 (like the real pointcloudset_test_tree.las)",
        "info shows the bounds of the points and warns that the "
        "header's disagree (before the fix: bounds 0..0)",
        0,
        _cloud(clouds.write_las_zero_bounds, "tree.las", "info"),
        (
            "disagree with the points' (x 300000..300009.99, y 4100000..4100009.99, z 50..57.99)",
            "300009.990",
        ),
    ),
    Case(
        "pcd-compressed-empty",
        "PCD binary_compressed whose compressed size is 0 (no data)",
        "error naming the field (before the fix: bounds from uninitialised memory)",
        2,
        _cloud(clouds.write_pcd_compressed_empty, "tree.pcd", "info"),
        ("compressed size is 0 bytes",),
    ),
    Case(
        "ply-face-before-vertex",
        "binary PLY with a face element before the vertices",
        "the vertices and their true bounds (before the fix: NaN bounds from info, MemoryError "
        "3.52 PiB from volume)",
        0,
        _cloud(clouds.write_ply_face_before_vertex, "tree.ply", "info"),
        ("249.750",),
    ),
    Case(
        "ply-face-before-vertex-short",
        "binary PLY declaring 500 faces before the vertices, holding 2",
        "error naming the element",
        2,
        _cloud(lambda p: clouds.write_ply_face_before_vertex(p, faces=500), "tree.ply", "volume"),
        ("'face' element before the vertices holds",),
    ),
    # -- drone photos ----------------------------------------------------------------------------
    Case(
        "drone-no-gps",
        "one photo without GPS EXIF",
        "error naming the photo",
        2,
        _drone(drone.without_gps),
        ("no GPS position in EXIF",),
    ),
    Case(
        "drone-duplicate",
        "one photo copied under a second name",
        "error naming both photos",
        2,
        _drone(drone.duplicated),
        ("duplicate of DJI_0001.JPG",),
    ),
    Case(
        "drone-truncated-jpeg",
        "one photo cut in half",
        "error naming the photo",
        2,
        _drone(drone.truncated_jpeg),
        ("not a readable JPEG",),
    ),
    Case(
        "drone-not-a-jpeg",
        "random bytes named .JPG",
        "error naming the file",
        2,
        _drone(drone.not_a_jpeg),
        ("not a readable JPEG",),
    ),
    Case(
        "drone-other-size",
        "one photo of another size",
        "error naming the photo and both sizes",
        2,
        _drone(drone.other_size),
        ("120x90 px", "160x120 px", "one size"),
    ),
    Case(
        "drone-too-few",
        "two photos",
        "error naming the folder and the minimum",
        2,
        _drone(drone.too_few, name_folder=True),
        ("at least 3 are needed",),
    ),
    Case(
        "drone-bad-in-run",
        "a photo without GPS given to 'run --drone-images'",
        "error before any LiDAR stage runs (checked up front)",
        2,
        _drone_in_run,
        ("no GPS position in EXIF",),
    ),
    # -- presets ---------------------------------------------------------------------------------
    Case(
        "preset-unknown-key",
        "top-level key 'colour'",
        "error naming the file and the key, listing the known keys",
        2,
        _preset("unknown-key-top"),
        ("unknown key 'colour'", "known keys"),
    ),
    Case(
        "preset-unknown-nested-key",
        "mapping.voxel instead of map_voxel_size",
        "error naming the file, section and key",
        2,
        _preset("unknown-key-nested"),
        (".mapping: unknown key 'voxel'",),
    ),
    Case(
        "preset-unknown-segmenter",
        "segment.method = 'meanshift'",
        "error listing the registered segmenters",
        2,
        _preset("unknown-plugin", "meanshift"),
        ("no segmenters plugin named 'meanshift'",),
    ),
    Case(
        "preset-unknown-parameter",
        "segment.params.epsilon for dbscan",
        "error naming the parameter and listing the segmenter's",
        2,
        _preset("unknown-plugin-parameter", "epsilon"),
        ("has no parameter 'epsilon'",),
    ),
    Case(
        "preset-wrong-type",
        'seed = "zero"',
        "error naming the file and key and the type",
        2,
        _preset("wrong-type-number"),
        (".seed: expected an integer, got 'zero'",),
    ),
    Case(
        "preset-wrong-container",
        'volume.methods = "alpha_shape" (not a list)',
        "error naming the key",
        2,
        _preset("wrong-type-table"),
        (".volume.methods: expected a list",),
    ),
    Case(
        "preset-negative-seed",
        "seed = -1",
        "error naming the key (before the fix: numpy ValueError traceback)",
        2,
        _preset("negative-seed", "config.seed"),
        ("non-negative integer",),
    ),
    Case(
        "preset-voxel-size-zero",
        "preprocess.voxel_size = 0",
        "error naming the setting, before mapping",
        2,
        _preset("voxel-size-zero", "preprocess.voxel_size"),
        ("must be positive",),
    ),
    Case(
        "preset-stem-band-reversed",
        "preprocess.stem_band = [0.8, 0.3]",
        "error naming the setting, before mapping",
        2,
        _preset("stem-band-reversed", "preprocess.stem_band"),
        ("0 <= low < high",),
    ),
    Case(
        "preset-alpha-negative",
        "volume alpha_shape alpha = -0.9",
        "error naming the method and parameter, before mapping",
        2,
        _preset("alpha-negative", "alpha_shape: alpha"),
        ("must be a positive number",),
    ),
    Case(
        "preset-range-limits-crossed",
        "mapping.min_range 70 m above max_range 60 m",
        "error naming both settings",
        2,
        _preset("range-limits-crossed", "mapping.min_range"),
        ("need 0 <= min_range < max_range",),
    ),
    Case(
        "preset-not-toml",
        "a preset file that is not valid TOML",
        "error naming the file, line and column",
        2,
        _preset("not-toml"),
        ("not valid TOML",),
    ),
    Case(
        "preset-unknown-name",
        "--preset walnut",
        "error listing the shipped presets",
        2,
        lambda root: (
            ["run", str(_valid_bag(root)), "--out", str(root / "o"), "--preset", "walnut"],
            "walnut",
        ),
        ("pistachio",),
    ),
    Case(
        "preset-bad-override",
        "--set preprocess.voxel_size=-1",
        "error naming the setting",
        2,
        _override("preprocess.voxel_size=-1", "preprocess.voxel_size"),
        ("must be positive",),
    ),
    # -- batch manifests and the orchard store ----------------------------------------------
    Case(
        "batch-id-absolute",
        'manifest session id = "/tmp/victim" (an absolute path)',
        "error naming the manifest and the id, before anything is written (it wrote into "
        "/tmp/victim, overwriting its trees.csv)",
        2,
        _batch(lambda root: manifests.toml_manifest(root, "/tmp/victim")),
        ("cannot name a folder",),
    ),
    Case(
        "batch-id-parent",
        'manifest session id = "../../x"',
        "error naming the manifest and "
        "the id; ids are names (letters, digits, '.', '_', '-'), never paths",
        2,
        _batch(lambda root: manifests.toml_manifest(root, "../../x")),
        ("cannot name a folder",),
    ),
    Case(
        "batch-ids-one-folder",
        'two sessions with ids "same" and "Same" (one folder where case is ignored)',
        "error naming both ids (the second overwrote the first)",
        2,
        _batch(lambda root: manifests.toml_manifest(root, "same", "Same")),
        ("names the folder of 'same'",),
    ),
    Case(
        "batch-csv-extra-cells",
        "CSV manifest with a row of more cells than the header",
        "error naming the row, its line and the header's columns (was exit 3, unknown key None)",
        2,
        _batch(lambda root: manifests.csv_manifest(root, b"s1,b.mcap,o,2025-04-01,oops\n")),
        ("has 5 cells, the header 4",),
    ),
    Case(
        "batch-csv-not-utf8",
        "CSV manifest saved as Latin-1 (an accented orchard name)",
        "error naming the file, line and byte (was exit 3); UTF-8 with BOM and UTF-16 are read",
        2,
        _batch(
            lambda root: manifests.csv_manifest(
                root, "s1,b.mcap,Höhe,2025-04-01\n".encode("latin-1")
            )
        ),
        ("not UTF-8 text (line 2",),
    ),
    Case(
        "store-cut-short",
        "orchard store (DuckDB) copied up to 40 % of its bytes",
        "error naming the store (was exit 3, DuckDB's IOException)",
        2,
        _store_cut,
        ("the store is damaged or cut short",),
    ),
    Case(
        "drone-one-place",
        "six photos taken at one GPS point (a hover)",
        "error at once naming the folder and the spread (200 such photos ran SfM for 4.5 min, "
        "then exit 3, leaving sfm/ behind)",
        2,
        _drone(drone.one_place, name_folder=True),
        ("all taken within",),
    ),
)

from bad_inputs.message_cases import MESSAGE_CASES  # noqa: E402 (they use Case)

CASES = CASES + MESSAGE_CASES
