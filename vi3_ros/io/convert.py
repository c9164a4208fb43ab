"""ROS 1 bag -> rosbag2 (MCAP) with rosbags' own converter, i.e. what ``rosbags-convert --src X.bag --dst Y
--dst-storage mcap`` does for users with real EuRoC bags (same defaults: format version 9, message types copied
from the source bag with ROS 2 headers)."""

from __future__ import annotations

from pathlib import Path

from rosbags.convert import ConverterError, convert

from vi3_core.errors import DataError


def convert_to_rosbag2(bag_path, dst, *, storage: str = "mcap", compress: str | None = None) -> Path:
    """Convert the ROS 1 bag ``bag_path`` into the rosbag2 directory ``dst`` (``metadata.yaml`` + storage file).

    ``storage``: "mcap" or "sqlite3"; ``compress``: None or "zstd" (file-mode compression). Returns ``dst``.
    """
    bag_path, dst = Path(bag_path), Path(dst)
    if storage not in ("mcap", "sqlite3"):
        raise ValueError(f"storage must be 'mcap' or 'sqlite3', got {storage!r}")
    if dst.exists():
        raise DataError(f"{dst}: already exists; rosbags-convert refuses to overwrite it")
    try:
        convert(srcs=[bag_path], dst=dst, dst_storage=storage, dst_version=9, compress=compress,
                compress_mode="file", default_typestore=None, typestore=None, exclude_topics=[],
                include_topics=[], exclude_msgtypes=[], include_msgtypes=[])
    except ConverterError as err:
        raise DataError(f"{bag_path}: rosbags could not convert it to {storage}: {err}") from err
    return dst
