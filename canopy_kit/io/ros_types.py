"""Message types a rosbags typestore lacks, registered from their ROS message definitions
(rosbags ships none of velodyne_msgs, livox_ros_driver(2) or ouster_ros)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any


def register_missing(typestore: Any, definitions: Mapping[str, str]) -> None:
    """Register each ``name -> .msg text`` of ``definitions`` the typestore does not know."""
    from rosbags.typesys import get_types_from_msg

    types: dict[str, Any] = {}
    for name, text in definitions.items():
        if name not in typestore.fielddefs:
            types.update(get_types_from_msg(text, name))
    if types:
        typestore.register(types)
