"""Test helpers: real EuRoC recordings made cheap to render, their cam0 at a quarter of its resolution."""

from __future__ import annotations

import shutil
from pathlib import Path

#: cam0 at 1/4 resolution (pixel centres scale): 188 x 120 renders some 16 times faster than 752 x 480
QUARTER = {"resolution: [752, 480]": "resolution: [188, 120]",
           "intrinsics: [458.654, 457.296, 367.215, 248.375]": "intrinsics: [114.6635, 114.324, 91.42875, 61.71875]"}


def quarter_cam0(yaml: str) -> str:
    """The text of EuRoC's cam0 ``sensor.yaml`` with the camera at 188 x 120."""
    for old, new in QUARTER.items():
        assert old in yaml, old
        yaml = yaml.replace(old, new)
    return yaml


def quarter_copy(src: Path, dst: Path) -> Path:
    """A copy of the ``mav0`` folder ``src`` (IMU, ground truth, calibration; no images) with cam0 at 188 x 120."""
    if not (dst / "cam0" / "sensor.yaml").is_file():
        for rel in ("imu0", "state_groundtruth_estimate0"):
            shutil.copytree(src / rel, dst / rel, dirs_exist_ok=True)
        (dst / "cam0").mkdir(parents=True, exist_ok=True)
        (dst / "body.yaml").write_bytes((src / "body.yaml").read_bytes())
        (dst / "cam0" / "sensor.yaml").write_text(quarter_cam0((src / "cam0" / "sensor.yaml").read_text()))
    return dst
