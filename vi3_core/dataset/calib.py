"""Camera calibration: intrinsics, distortion and the camera pose in the body (IMU) frame.

Two file formats are read (detected by content):

- EuRoC ``cam0/sensor.yaml``: ``intrinsics: [fu, fv, cu, cv]``, ``distortion_model: radial-tangential``,
  ``distortion_coefficients: [k1, k2, p1, p2]``, ``resolution: [w, h]``, ``T_BS`` (camera pose in the body frame).
- Kalibr ``camchain-imucam.yaml``: ``camN: {intrinsics, distortion_model: radtan | equidistant | none,
  distortion_coeffs, resolution, T_cam_imu, timeshift_cam_imu}``; ``T_cam_imu`` maps IMU points into the camera, so
  ``T_BC`` is its inverse; ``timeshift_cam_imu`` (s, ``t_imu = t_cam + timeshift``) becomes ``time_offset``.

Every field is checked on load (a CalibrationError names the file, the field and its value): positive focal lengths,
a principal point inside the image, finite coefficients in the number the distortion model takes, a rigid camera pose
(a rotation, not a mirror), a finite time offset within a second.

Undistortion keeps the raw intrinsics ``K`` for the undistorted pinhole image (same size): with EuRoC's barrel
distortion every undistorted pixel then has a source pixel inside the raw image.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from vi3_core import so3
from vi3_core.errors import CalibrationError, yaml_problem
from vi3_core.paths import missing_reason

DIST_MODELS = ("radtan", "equidistant", "none")
MAX_TIME_OFFSET_S = 1.0  # s; the largest camera-IMU time offset accepted (the time_offset parameter's range)
_EUROC_MODELS = {"radial-tangential": "radtan", "radtan": "radtan", "equidistant": "equidistant", "none": "none"}


@dataclass(frozen=True)
class Undistorter:
    """Remaps a raw (distorted) image onto the pinhole image of intrinsics ``K`` [3,3] (same size).

    map_x, map_y: [H,W] float32 raw-pixel coordinates of each undistorted pixel centre; None for a camera without
    distortion (a rectified stream), whose raw image is the pinhole image already: ``apply`` copies it, the same bits as
    a remap through the identity maps for the images the pipeline undistorts (finite, of the calibrated size; a NaN
    border with INTER_NEAREST only), at no cost (the remap took 2.3 ms a 1280x720 frame).
    """

    K: np.ndarray
    map_x: np.ndarray | None
    map_y: np.ndarray | None

    def apply(self, image: np.ndarray, *, interpolation: int = cv2.INTER_LINEAR,
              border_value: float = 0.0) -> np.ndarray:
        """Undistorted copy of ``image`` [H,W] or [H,W,C] (same dtype); pixels that map outside the raw image get
        ``border_value``."""
        if self.map_x is None:
            return image.copy()
        return cv2.remap(image, self.map_x, self.map_y, interpolation, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=border_value)


@dataclass(frozen=True)
class CameraCalib:
    """One camera: K [3,3] raw intrinsics, distortion ``dist_model`` with coefficients ``dist`` [k],
    size (width, height) in pixels, ``T_BC`` [4,4] camera pose in the body (IMU) frame, frame rate in Hz,
    ``time_offset`` s, the camera-IMU clock offset (t_imu = t_cam + time_offset; Kalibr's ``timeshift_cam_imu``)."""

    K: np.ndarray
    dist_model: str
    dist: np.ndarray
    size: tuple[int, int]
    T_BC: np.ndarray
    rate_hz: float | None = None
    time_offset: float = 0.0

    def __post_init__(self) -> None:
        if self.dist_model not in DIST_MODELS:
            raise CalibrationError(f"distortion model {self.dist_model!r} is not one of {DIST_MODELS}")
        expected = {"radtan": 4, "equidistant": 4, "none": 0}[self.dist_model]
        if len(self.dist) != expected:
            raise CalibrationError(f"{self.dist_model} distortion needs {expected} coefficients, got {len(self.dist)}")
        problem = self._problem()
        if problem is not None:
            raise CalibrationError(problem)

    def _problem(self) -> str | None:
        """What makes this calibration unusable (naming the field and its value), or None."""
        w, h = self.size
        if not (isinstance(w, int | np.integer) and isinstance(h, int | np.integer) and w > 0 and h > 0):
            return f"resolution {list(self.size)} is not two positive integers [width, height]"
        fu, fv, cu, cv = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        for name, value in (("fu", fu), ("fv", fv)):
            if not (np.isfinite(value) and value > 0):
                return f"focal length {name} = {value:g} (intrinsics) must be finite and > 0"
        for name, value, limit in (("cu", cu, w), ("cv", cv, h)):
            if not (np.isfinite(value) and 0 <= value <= limit):
                return f"principal point {name} = {value:g} (intrinsics) lies outside the image [0, {limit}]"
        if not np.all(np.isfinite(self.dist)):
            return f"distortion coefficients {np.asarray(self.dist).tolist()} are not all finite"
        if not np.all(np.isfinite(self.T_BC)):
            return "T_BC (camera pose in the body frame) has NaN/Inf entries"
        if self.rate_hz is not None and not (np.isfinite(self.rate_hz) and self.rate_hz > 0):
            return f"rate_hz = {self.rate_hz:g} must be finite and > 0"
        if not (np.isfinite(self.time_offset) and abs(self.time_offset) <= MAX_TIME_OFFSET_S):
            return (f"timeshift_cam_imu = {self.time_offset:g} s (the camera-IMU time offset) must be a finite number "
                    f"within [-{MAX_TIME_OFFSET_S:g}, {MAX_TIME_OFFSET_S:g}] s")
        return None

    def check_frame(self, image: np.ndarray) -> str | None:
        """Why a raw frame [H,W] or [H,W,C] cannot be undistorted with this calibration (its size is not the
        calibrated resolution), or None."""
        h, w = np.shape(image)[:2] if np.ndim(image) >= 2 else (0, 0)
        if (w, h) != tuple(self.size):
            return f"frame is {w}x{h} but the calibration is for {self.size[0]}x{self.size[1]}"
        return None

    def undistorter(self) -> Undistorter:
        """Built once per calibration (cached): maps from the undistorted pinhole image to the raw image."""
        cached = self.__dict__.get("_undistorter")
        if cached is None:
            cached = self.__dict__["_undistorter"] = self._build_undistorter()
        return cached

    def _build_undistorter(self) -> Undistorter:
        w, h = self.size
        K = self.K.copy()
        # no distortion: the identity (an equidistant lens with zero coefficients still maps angles, not tangents)
        if self.dist_model != "equidistant" and not np.any(self.dist):
            return Undistorter(K, None, None)
        if self.dist_model == "equidistant":
            mx, my = cv2.fisheye.initUndistortRectifyMap(self.K, self.dist, np.eye(3), K, (w, h), cv2.CV_32FC1)
        else:
            mx, my = cv2.initUndistortRectifyMap(self.K, self._cv_dist, None, K, (w, h), cv2.CV_32FC1)
        return Undistorter(K, mx, my)

    @property
    def _cv_dist(self) -> np.ndarray:
        return self.dist if self.dist_model == "radtan" else np.zeros(4)

    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Normalised undistorted image coordinates [N,2] -> raw pixel coordinates [N,2]."""
        pts = np.concatenate([xy, np.ones((len(xy), 1))], 1).reshape(-1, 1, 3).astype(np.float64)
        if self.dist_model == "equidistant":
            out = cv2.fisheye.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self.dist)[0]
        else:
            out = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self._cv_dist)[0]
        return out.reshape(-1, 2)

    def undistort_points(self, uv: np.ndarray) -> np.ndarray:
        """Raw pixel coordinates [N,2] -> normalised undistorted coordinates [N,2] (iterated to 1e-12)."""
        pts = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        if self.dist_model == "equidistant":
            out = cv2.fisheye.undistortPoints(pts, self.K, self.dist, criteria=crit)
        else:
            out = cv2.undistortPoints(pts, self.K, self._cv_dist, criteria=crit)
        return out.reshape(-1, 2)


def _matrix(value, name: str, path: Path) -> np.ndarray:
    """A 4x4 matrix from EuRoC's {rows, cols, data} or Kalibr's nested list."""
    data = value.get("data") if isinstance(value, dict) else value
    try:
        T = np.asarray(data, dtype=np.float64).reshape(4, 4)
    except (TypeError, ValueError) as err:
        raise CalibrationError(f"{path}: {name} is not a 4x4 matrix ({err})") from None
    if not np.allclose(T[3], [0, 0, 0, 1]) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-4):
        raise CalibrationError(f"{path}: {name} is not a rigid transform:\n{T}")
    det = float(np.linalg.det(T[:3, :3]))
    if det < 0:
        raise CalibrationError(f"{path}: {name} is a mirror, not a rotation (determinant of its rotation part "
                               f"{det:.3f}; a camera pose has +1): check the sign of one axis")
    # a rotation written to 8 digits is 1e-6 from orthonormal; every chained clip composes it twice
    T[:3, :3] = so3.nearest_rotation(T[:3, :3])
    return T


def _build(entry: dict, *, intr_key: str, dist_key: str, T_BC: np.ndarray, path: Path) -> CameraCalib:
    for key in (intr_key, "resolution"):
        if key not in entry:
            raise CalibrationError(f"{path}: missing {key!r}")
    if entry.get("camera_model", "pinhole") != "pinhole":
        raise CalibrationError(f"{path}: camera_model {entry['camera_model']!r} is not supported (pinhole only)")
    fu, fv, cu, cv = _numbers(entry[intr_key], intr_key, 4, float, path)
    dist = np.asarray(entry.get(dist_key, []) or [], dtype=np.float64)
    if "distortion_model" not in entry and dist.size:
        raise CalibrationError(f"{path}: distortion_model is missing but {dist_key} has {dist.size} coefficients; "
                               f"name the model (one of {sorted(_EUROC_MODELS)})")
    model = _EUROC_MODELS.get(str(entry.get("distortion_model", "none")))
    if model is None:
        raise CalibrationError(f"{path}: distortion_model {entry['distortion_model']!r} is not one of "
                               f"{sorted(_EUROC_MODELS)}")
    w, h = _numbers(entry["resolution"], "resolution", 2, int, path)
    rate = entry.get("rate_hz")
    K = np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])
    try:
        return CameraCalib(K, model, dist, (w, h), T_BC, None if rate is None else float(rate),
                           float(entry.get("timeshift_cam_imu", 0.0)))
    except (CalibrationError, TypeError, ValueError) as err:
        raise CalibrationError(f"{path}: {err}") from None


def _numbers(value, key: str, count: int, kind: type, path: Path) -> list:
    """``count`` numbers of type ``kind`` from the list ``value`` of field ``key``; CalibrationError naming it."""
    try:
        out = [kind(x) for x in value]
        if kind is int and any(float(x) != int(x) for x in value):
            raise ValueError
    except (TypeError, ValueError):
        out = []
    if len(out) != count:
        raise CalibrationError(f"{path}: {key!r} must be a list of {count} {kind.__name__} numbers, got {value!r}")
    return out


def _document(path: Path) -> dict:
    """The YAML mapping of a calibration file; CalibrationError naming the file when it cannot be read as one."""
    if path.is_dir():
        raise CalibrationError(f"{path}: is a directory, not a calibration file (EuRoC sensor.yaml or Kalibr "
                               "camchain YAML)")
    if not path.is_file():
        raise CalibrationError(f"{path}: calibration file {missing_reason(path)}")
    try:
        raw = path.read_text()
    except UnicodeDecodeError:
        raise CalibrationError(f"{path}: not a text file (binary content); expected an EuRoC sensor.yaml or a "
                               "Kalibr camchain YAML") from None
    except OSError as err:
        raise CalibrationError(f"{path}: cannot read it ({err.strerror})") from None
    # EuRoC ships some files with OpenCV's "%YAML:1.0" directive, which PyYAML rejects (blanked: lines keep numbers).
    text = "\n".join("" if line.startswith("%YAML") else line for line in raw.splitlines())
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise CalibrationError(f"{path}: not valid YAML: {yaml_problem(err)}") from None
    if not isinstance(doc, dict):
        raise CalibrationError(f"{path}: expected a YAML mapping, got {type(doc).__name__}")
    return doc


def load_calib(path, *, camera: str = "cam0") -> CameraCalib:
    """Read an EuRoC ``sensor.yaml`` or a Kalibr camchain(-imucam) YAML (``camera`` picks the Kalibr entry)."""
    path = Path(path)
    doc = _document(path)
    if "T_BS" in doc:
        if doc.get("sensor_type", "camera") != "camera":
            raise CalibrationError(f"{path}: sensor_type is {doc['sensor_type']!r}, not a camera")
        return _build(doc, intr_key="intrinsics", dist_key="distortion_coefficients",
                      T_BC=_matrix(doc["T_BS"], "T_BS", path), path=path)
    if isinstance(doc.get(camera), dict):
        entry = doc[camera]
        if "T_cam_imu" not in entry:
            raise CalibrationError(f"{path}: {camera} has no T_cam_imu (a camchain without IMU extrinsics)")
        T_BC = so3.inv_T(_matrix(entry["T_cam_imu"], f"{camera}.T_cam_imu", path))
        return _build(entry, intr_key="intrinsics", dist_key="distortion_coeffs", T_BC=T_BC, path=path)
    raise CalibrationError(f"{path}: neither an EuRoC sensor.yaml (no T_BS) nor a Kalibr camchain "
                           f"(no {camera!r} entry); top-level keys: {sorted(doc)}")


def write_euroc_sensor_yaml(calib: CameraCalib, path, *, comment: str = "") -> None:
    """Write ``calib`` as an EuRoC ``cam0/sensor.yaml`` (radtan or none distortion)."""
    if calib.dist_model == "equidistant":
        raise CalibrationError(f"{path}: EuRoC sensor.yaml has no equidistant model; write a Kalibr camchain")
    K = calib.K
    doc = {
        "sensor_type": "camera",
        "comment": comment,
        "T_BS": {"cols": 4, "rows": 4, "data": [float(x) for x in calib.T_BC.reshape(-1)]},
        "rate_hz": calib.rate_hz,
        "resolution": list(calib.size),
        "camera_model": "pinhole",
        "intrinsics": [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])],
        "distortion_model": "radial-tangential" if calib.dist_model == "radtan" else "none",
        "distortion_coefficients": [float(x) for x in calib.dist],
    }
    Path(path).write_text(yaml.safe_dump(doc, sort_keys=False, default_flow_style=None))


def kalibr_camchain(calib: CameraCalib, *, camera: str = "cam0", rostopic: str = "/cam0/image_raw") -> str:
    """``calib`` as the text of a Kalibr ``camchain-imucam.yaml`` (``T_cam_imu`` = inverse of ``T_BC``,
    ``timeshift_cam_imu`` = ``time_offset``)."""
    K = calib.K
    entry = {
        "T_cam_imu": so3.inv_T(calib.T_BC).tolist(),
        "cam_overlaps": [],
        "camera_model": "pinhole",
        "distortion_coeffs": [float(x) for x in calib.dist],
        "distortion_model": calib.dist_model,
        "intrinsics": [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])],
        "resolution": list(calib.size),
        "rostopic": rostopic,
        "timeshift_cam_imu": float(calib.time_offset),
    }
    return yaml.safe_dump({camera: entry}, sort_keys=False, default_flow_style=None)


def corrected_kalibr(path, calib: CameraCalib, *, camera: str = "cam0") -> str | None:
    """The text of the Kalibr camchain ``path`` with ``camera``'s ``T_cam_imu`` and ``timeshift_cam_imu`` replaced by
    ``calib``'s and every other field kept as the file has it (its comments excepted); None when ``path`` is not a
    Kalibr camchain (an EuRoC sensor.yaml)."""
    path = Path(path)
    doc = _document(path)
    entry = doc.get(camera)
    if not isinstance(entry, dict) or "T_cam_imu" not in entry:
        return None
    entry["T_cam_imu"] = so3.inv_T(calib.T_BC).tolist()
    entry["timeshift_cam_imu"] = float(calib.time_offset)
    return yaml.safe_dump(doc, sort_keys=False, default_flow_style=None)


def write_kalibr_camchain(calib: CameraCalib, path, *, camera: str = "cam0", rostopic: str = "/cam0/image_raw") -> None:
    """Write ``kalibr_camchain(calib)`` to ``path``."""
    Path(path).write_text(kalibr_camchain(calib, camera=camera, rostopic=rostopic))
