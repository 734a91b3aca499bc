"""Make data/samples/ouster_sdk_reference.npz: Ouster packets written and decoded by ouster-sdk.

ouster-sdk cannot share canopy-kit's venv (it pins rosbags 0.9.23, click < 8.1.8, flask 3.0),
so run this in a venv of its own, on metadata JSON that canopy-kit's simulator wrote::

    python -m venv /tmp/osdk && /tmp/osdk/bin/pip install ouster-sdk==1.0.1
    /tmp/osdk/bin/python scripts/make_ouster_reference.py LEGACY=meta_512x20.json \
        RNG19_RFL8_SIG16_NIR16=meta_1024x10.json

For each profile: ranges drawn at random (40 % returns) into a LidarScan, the SDK's
``scan_to_packets`` (its packet writer), the first three packets kept with the SDK's
``XYZLut`` points of their columns (sensor frame) and the SDK's metadata JSON.
tests/test_ouster.py decodes the packets with canopy-kit and compares.
"""

import json
import sys
import warnings
from pathlib import Path

import numpy as np

warnings.simplefilter("ignore")  # the SDK's deprecation notices

import ouster.sdk.core as c  # noqa: E402

OUT = Path(__file__).parents[1] / "data" / "samples" / "ouster_sdk_reference.npz"
KEEP = 3  # packets


def main(pairs: list[str]) -> None:
    rng = np.random.default_rng(7)
    out = {}
    for pair in pairs:
        profile, path = pair.split("=", 1)
        info = c.SensorInfo(Path(path).read_text())
        assert str(info.format.udp_profile_lidar) == profile, info.format.udp_profile_lidar
        fmt = c.PacketFormat(info)
        scan = c.LidarScan(info)
        h, w = scan.h, scan.w
        ranges = (rng.uniform(500, 60000, (h, w)) * (rng.random((h, w)) < 0.4)).astype(np.uint32)
        scan.field(c.ChanField.RANGE)[:] = ranges
        scan.timestamp[:] = 5_000_000_000 + np.arange(w) * (1_000_000_000 // (w * info.format.fps))
        scan.measurement_id[:] = np.arange(w)
        scan.status[:] = 0xFFFFFFFF if profile == "LEGACY" else 1
        scan.frame_id = 321
        packets = c.scan_to_packets(scan, fmt, 0, 0)
        columns = KEEP * info.format.columns_per_packet
        xyz = c.XYZLut(info, use_extrinsics=False)(scan.field(c.ChanField.RANGE))
        out[f"{profile}_packets"] = np.stack([np.asarray(p.buf) for p in packets[:KEEP]])
        out[f"{profile}_xyz"] = xyz[:, :columns, :]
        out[f"{profile}_range_mm"] = ranges[:, :columns]
        out[f"{profile}_metadata"] = np.array(info.to_json_string())
        print(profile, fmt.lidar_packet_size, json.loads(info.to_json_string())["config_params"])
    np.savez_compressed(OUT, **out)


if __name__ == "__main__":
    main(sys.argv[1:])
