"""The camera-IMU time offset between the ``time_offset`` parameter and a calibration file: one rule for the node and
replay.

A Kalibr camchain-imucam states the offset as ``timeshift_cam_imu`` (``CameraCalib.time_offset``, s, ``t_imu = t_cam
+ time_offset``). The calibration's value is used while the parameter is at its default, 0; a non-zero parameter
overrides it, and says so when the calibration states another non-zero offset. (A parameter of 0 cannot override a
non-zero timeshift: edit the calibration instead.)
"""

from __future__ import annotations

from vi3_core.dataset.calib import CameraCalib
from vi3_ros.settings import Settings


def resolve_time_offset(settings: Settings, calib: CameraCalib) -> tuple[Settings, str]:
    """``settings`` with ``time_offset`` (s) per the rule above, and a note for the user ("" when there is nothing to
    say)."""
    given, stated = settings.buffer.time_offset, float(calib.time_offset)
    if given == 0.0:
        return settings.replace(time_offset=stated), ""
    if stated != 0.0 and given != stated:
        return settings, (f"parameter time_offset = {given:g} s overrides the calibration's timeshift_cam_imu = "
                          f"{stated:g} s")
    return settings, ""
