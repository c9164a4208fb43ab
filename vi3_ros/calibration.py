"""The camera calibration of a stream, assembled from a calibration file and live messages (CameraInfo, /tf_static),
and the undistortion of a raw clip with it."""

from __future__ import annotations

import dataclasses

import numpy as np

from vi3_core.dataset.calib import CameraCalib
from vi3_core.errors import CalibrationError
from vi3_core.types import Clip
from vi3_ros.clip_buffer import RawClip


def calib_from_camera_info(K: np.ndarray, dist_model: str, dist: np.ndarray, size: tuple[int, int],
                           T_BC: np.ndarray) -> CameraCalib:
    """A CameraCalib from ``msg_adapters.camera_info.camera_info_to_calib``'s output and T_BC [4,4].

    plumb_bob maps to radtan when k3 = 0 (radtan has k1, k2, p1, p2); all-zero coefficients mean no distortion, but for
    an equidistant (fisheye) lens, which maps angles to radii whatever its coefficients."""
    dist = np.asarray(dist, dtype=np.float64)
    if dist_model == "equidistant":
        return CameraCalib(K, "equidistant", dist if len(dist) else np.zeros(4), size, T_BC)
    if not dist.any():
        return CameraCalib(K, "none", np.zeros(0), size, T_BC)
    if dist_model in ("plumb_bob", "rational_polynomial") and not dist[4:].any():
        return CameraCalib(K, "radtan", dist[:4], size, T_BC)
    raise CalibrationError(f"CameraInfo distortion {dist_model} with coefficients {dist.tolist()} has terms beyond "
                           "k1, k2, p1, p2 that the undistorter does not model")


class Calibration:
    """The current camera calibration, assembled from a calibration file and/or live messages.

    Intrinsics come from CameraInfo (``set_intrinsics``) or the file; T_BC from /tf_static (``set_extrinsics``) or
    the file. ``current()`` raises CalibrationError naming what is still missing."""

    def __init__(self, file_calib: CameraCalib | None = None) -> None:
        self._file = file_calib
        self._intrinsics: tuple | None = None
        self._T_BC: np.ndarray | None = None
        self._cached: CameraCalib | None = file_calib

    def set_intrinsics(self, K: np.ndarray, dist_model: str, dist: np.ndarray, size: tuple[int, int]) -> None:
        new = (np.asarray(K, np.float64), dist_model, np.asarray(dist, np.float64), tuple(size))
        old = self._intrinsics
        if old is None or not (np.array_equal(old[0], new[0]) and old[1] == new[1] and np.array_equal(old[2], new[2])
                               and old[3] == new[3]):
            self._intrinsics, self._cached = new, None

    def set_extrinsics(self, T_BC: np.ndarray) -> None:
        T_BC = np.asarray(T_BC, np.float64)
        if self._T_BC is None or not np.array_equal(self._T_BC, T_BC):
            self._T_BC, self._cached = T_BC, None

    def size(self) -> tuple[int, int] | None:
        """(width, height) of the frames the current intrinsics are for, or None while there are none."""
        if self._intrinsics is not None:
            return tuple(self._intrinsics[3])
        return None if self._file is None else tuple(self._file.size)

    def current(self) -> CameraCalib:
        if self._cached is not None:
            return self._cached
        T_BC = self._T_BC if self._T_BC is not None else (self._file.T_BC if self._file is not None else None)
        if self._intrinsics is None and self._file is None:
            raise CalibrationError("no camera intrinsics yet: no CameraInfo received and no calib_file given")
        if T_BC is None:
            raise CalibrationError("no camera-IMU extrinsics: no /tf_static imu_frame -> camera_frame and no "
                                   "calib_file given")
        if self._intrinsics is not None:
            self._cached = calib_from_camera_info(*self._intrinsics, T_BC)
        else:
            self._cached = dataclasses.replace(self._file, T_BC=T_BC)
        return self._cached


class FrameMisfit(CalibrationError):
    """A frame of a clip does not fit the calibration (``vi3_core.dataset.calib.CameraCalib.check_frame``)."""


def make_clip(raw: RawClip, calib: CameraCalib) -> Clip:
    """Undistort the raw frames of ``raw`` with ``calib`` into a Clip (K of the undistorted images). Raises
    FrameMisfit naming the first frame whose size is not the calibrated one."""
    for i, im in enumerate(raw.images):
        problem = calib.check_frame(im)
        if problem is not None:
            raise FrameMisfit(f"frame {i} (stamp {int(raw.stamps_ns[i])} ns): {problem}")
    und = calib.undistorter()
    images = np.stack([und.apply(im) for im in raw.images])
    return Clip(stamps=raw.stamps, images=images, K=und.K, T_BC=calib.T_BC, imu=raw.imu, imu_history=raw.imu_history,
                stamps_ns=raw.stamps_ns)


def frame_problem(image: np.ndarray) -> str | None:
    """Why the pipeline cannot take a raw frame whatever the calibration (not [H,W] or [H,W,3] uint8, or empty),
    or None."""
    shape, dtype = np.shape(image), np.asarray(image).dtype
    if dtype != np.uint8:
        return f"frame of dtype {dtype} (shape {list(shape)}): the pipeline takes 8-bit mono or RGB frames"
    if not (len(shape) == 2 or (len(shape) == 3 and shape[2] == 3)) or 0 in shape:
        return f"frame of shape {list(shape)}: the pipeline takes [H,W] mono or [H,W,3] RGB frames"
    return None


__all__ = ["Calibration", "FrameMisfit", "calib_from_camera_info", "frame_problem", "make_clip"]
