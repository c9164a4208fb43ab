"""A wrong rig calibration on purpose (``vi3 eval --calib-error``): what a user's own camera mount and clocks give when
the calibration file is off, for measuring the self-calibration (``vi3_core.online.calibration``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from vi3_core import so3
from vi3_core.dataset.calib import MAX_TIME_OFFSET_S
from vi3_core.dataset.sequence import Sequence
from vi3_core.sim.visual import parse_floats


@dataclass(frozen=True)
class RigError:
    """rotation_deg [3]: the true mount is the configured one turned by Exp(rotation) about the body axes (the
    configuration is off by that; a rotation vector of at most 180 deg); imu_delay_s: the IMU's stamps are this late
    against the camera's (at most MAX_TIME_OFFSET_S either way)."""

    rotation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    imu_delay_s: float = 0.0

    @staticmethod
    def parse(text: str) -> RigError:
        """"RX_DEG,RY_DEG,RZ_DEG[,IMU_DELAY_MS]" -> RigError; ValueError naming the text."""
        form = "RX_DEG,RY_DEG,RZ_DEG[,IMU_DELAY_MS], finite"
        values = parse_floats(text, (3, 4), "calibration error", form, "3,0,0,20")
        angle = float(np.linalg.norm(values[:3]))
        delay_ms = values[3] if len(values) == 4 else 0.0
        if angle > 180.0:  # a rotation vector: longer ones are the same rotations as shorter ones, so one is asked
            raise ValueError(f"calibration error {text!r}: the rotation (RX, RY, RZ) is {angle:g} deg about its axis; "
                             "give one of at most 180 deg (a longer one is a shorter one the other way round)")
        if abs(delay_ms) > MAX_TIME_OFFSET_S * 1e3:
            raise ValueError(f"calibration error {text!r}: IMU_DELAY_MS {delay_ms:g} is outside "
                             f"[-{MAX_TIME_OFFSET_S * 1e3:g}, {MAX_TIME_OFFSET_S * 1e3:g}] ms (time_offset's range)")
        return RigError(tuple(values[:3]), delay_ms * 1e-3)

    @property
    def rotation(self) -> np.ndarray:
        """[3] rad."""
        return np.radians(np.asarray(self.rotation_deg, np.float64))

    def apply(self, seq: Sequence) -> Sequence:
        """``seq`` as a user with this error sees it: its calibration's mount turned back by the rotation (the truth is
        the file's), its IMU stamps delayed; images and ground truth as recorded."""
        T_BC = so3.turn_T(seq.calib.T_BC, -self.rotation)
        imu = dataclasses.replace(seq.imu, t=seq.imu.t + self.imu_delay_s)
        return dataclasses.replace(seq, calib=dataclasses.replace(seq.calib, T_BC=T_BC), imu=imu)


__all__ = ["RigError"]
