"""A wrong rig calibration on purpose (``vi3 eval --calib-error``): what a user's own camera mount and clocks give when
the calibration file is off, for measuring the self-calibration (``vi3_core.online.calibration``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from vi3_core import so3
from vi3_core.dataset.sequence import Sequence
from vi3_core.sim.visual import parse_floats


@dataclass(frozen=True)
class RigError:
    """rotation_deg [3]: the true mount is the configured one turned by Exp(rotation) about the body axes (the
    configuration is off by that); imu_delay_s: the IMU's stamps are this late against the camera's."""

    rotation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    imu_delay_s: float = 0.0

    @staticmethod
    def parse(text: str) -> RigError:
        """"RX_DEG,RY_DEG,RZ_DEG[,IMU_DELAY_MS]" -> RigError; ValueError naming the text."""
        values = parse_floats(text, (3, 4), "calibration error", "RX_DEG,RY_DEG,RZ_DEG[,IMU_DELAY_MS], finite",
                              "3,0,0,20")
        return RigError(tuple(values[:3]), values[3] * 1e-3 if len(values) == 4 else 0.0)

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
