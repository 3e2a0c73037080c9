"""A rosbags typestore for ROS 2 Jazzy extended with our message packages.

``vision_msgs``, ``lidar_quality_msgs`` and ``autoware_perception_msgs`` are registered
from their ``.msg`` files as installed in the ament index (the workspace's, or a system
copy), else from the
repository's ``ros2_ws/src``: never from a second copy of the definitions.
"""
from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path

PACKAGES = ("vision_msgs", "lidar_quality_msgs", "autoware_perception_msgs")
_REPO_SRC = Path(__file__).resolve().parents[2] / "ros2_ws" / "src"


def msg_dir(package: str) -> Path:
    """Directory of ``package``'s .msg files: ament index first, then the repository."""
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        marker = Path(prefix) / "share" / "ament_index" / "resource_index" / "packages" / package
        if prefix and marker.exists():
            return Path(prefix) / "share" / package / "msg"
    candidate = _REPO_SRC / package / "msg"
    if candidate.is_dir():
        return candidate
    raise FileNotFoundError(f"no .msg files of {package}: not in AMENT_PREFIX_PATH nor {candidate}")


@lru_cache(maxsize=1)
def typestore():
    """The Jazzy typestore with ``PACKAGES`` registered (cached: types are immutable)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for package in PACKAGES:
        for path in sorted(msg_dir(package).glob("*.msg")):
            types.update(get_types_from_msg(path.read_text(), f"{package}/msg/{path.stem}"))
    store.register(types)
    return store
