"""What a real camera's sensor and electronics do to the ideal image: rolling shutter, motion blur, auto exposure and
gain, vignetting, sensor noise and JPEG, sized from a handheld RealSense recording (docs/evaluation.md).

The renderer gives each image row its own pose (rolling shutter: ``vi3_core.rolling_shutter.row_times``), at the
middle of that row's exposure; ``blur`` then integrates the exposure with the scene's exact depth: every pixel is
moved as the camera moves during the exposure (``blur_samples`` instants, the image warped to each with ``cv2.remap``
and averaged), which is exact for a static scene away from occlusion edges. ``Exposure`` runs the camera's auto
exposure over the frames: the scene's brightness drifts (lamps, a window, the camera turning towards dark furniture),
the exposure follows it with a lag and sets the frame interval when it needs more light than a frame at full rate
gives (a RealSense in auto-exposure priority drops from 30 to 16.7 Hz in a dim room). ``finish`` turns radiance into
the stored mono8 frame: vignetting, exposure times gain, shot and read noise, quantisation, JPEG.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class SensorModel:
    """readout_s: rolling shutter, the time from the first row's exposure to the last's (0: global shutter);
    exposure_s: the longest exposure (the auto exposure shortens it in bright light), blur_samples: instants the
    exposure is integrated over; frame_intervals_s: the intervals the camera runs at, fastest first (the auto exposure
    picks the fastest whose interval holds the exposure it needs); target_grey: the mean grey level the auto exposure
    aims at, ae_lag: the share of the error it corrects per frame; brightness: the scene's log brightness, a mean-
    reverting walk (mean, standard deviation, correlation time s: the light and where the camera looks);
    vignetting: relative fall-off at the image corner; read_noise: grey levels (1-sigma), shot_noise: grey levels at
    full scale (the Poisson part, sqrt of the signal); jpeg_quality: 0-100 (0: no JPEG); drop_rate: frames lost at
    random; gap_rate: per second, a stall of ``gap_s`` s (USB, a busy host)."""

    readout_s: float = 0.0
    exposure_s: float = 0.0
    blur_samples: int = 1
    frame_intervals_s: tuple[float, ...] = (0.05,)
    target_grey: float = 86.0
    ae_lag: float = 0.3
    brightness: tuple[float, float, float] = (0.0, 0.0, 10.0)
    vignetting: float = 0.0
    read_noise: float = 0.0
    shot_noise: float = 0.0
    jpeg_quality: int = 0
    drop_rate: float = 0.0
    gap_rate: float = 0.0
    gap_s: tuple[float, float] = (0.2, 0.45)

    @property
    def ideal(self) -> bool:
        """Whether the sensor changes nothing (a global-shutter, noise-free, fixed-rate camera: EuRoC's renders)."""
        return self == SensorModel(frame_intervals_s=self.frame_intervals_s)


#: A RealSense's colour stream in a dim room, as the DM-VIO dataset's handheld recording shows it: JPEG quality 95, a
#: noise after compression of 0.57 grey levels by Immerkaer's estimate at the front end's 1024 px (these read and shot
#: noises give 0.63 in the bedroom scene), a mean grey of 86 (p10-p90: 75-91), 30 / 25 / 20 / 16.7 Hz by the light
#: (14 / 14 / 19 / 53 % of its intervals), 8 frames lost in 2382 and 6 stalls of 0.23-0.43 s in 124 s.
REALSENSE = SensorModel(readout_s=0.025, exposure_s=0.058, blur_samples=5,
                        frame_intervals_s=(1 / 30, 1 / 25, 1 / 20, 1 / 16.67), target_grey=86.0, ae_lag=0.3,
                        brightness=(0.1, 0.35, 10.0), vignetting=0.25, read_noise=1.0, shot_noise=2.5, jpeg_quality=95,
                        drop_rate=0.0035, gap_rate=0.05)


def blur(image: np.ndarray, depth: np.ndarray, K: np.ndarray, rows_T_WC: np.ndarray,
         pose_at: Callable[[np.ndarray], np.ndarray], row_t: np.ndarray, exposure_s: float,
         samples: int) -> np.ndarray:
    """The exposure of ``image`` [H,W] (float32 radiance at each row's mid-exposure pose ``rows_T_WC`` [H,4,4], of an
    undistorted pinhole camera K [3,3], with z-depth ``depth`` [H,W] m) integrated over ``exposure_s`` at ``samples``
    instants: ``pose_at(t [k]) -> T_WC [k,4,4]`` gives the camera's pose at any time, ``row_t`` [H] each row's
    mid-exposure time. Each instant's image is the frame warped by the motion since mid-exposure (every pixel's
    point projected from where it was), sampled back (a pixel takes the value from where it moved from, to first
    order); pixels without depth (sky, a miss) keep their value."""
    if samples <= 1 or exposure_s <= 0.0:
        return image
    H, W = image.shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    z = np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)
    X = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])  # [3,H,W] in each row's camera
    out = np.zeros_like(image, dtype=np.float32)
    for tau in (np.arange(samples) + 0.5) / samples - 0.5:
        T = pose_at(row_t + tau * exposure_s)  # [H,4,4]
        dT = np.linalg.inv(T) @ rows_T_WC  # row camera at mid-exposure -> at this instant
        R, t = dT[:, :3, :3].astype(np.float32), dT[:, :3, 3].astype(np.float32)
        Y = np.einsum("rij,jrc->irc", R, X) + t.T[:, :, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            pu = K[0, 0] * Y[0] / Y[2] + K[0, 2]
            pv = K[1, 1] * Y[1] / Y[2] + K[1, 2]
        moved = (z > 0) & np.isfinite(pu) & np.isfinite(pv)
        map_x = np.where(moved, 2 * u - pu, u).astype(np.float32)  # where the pixel's content comes from
        map_y = np.where(moved, 2 * v - pv, v).astype(np.float32)
        out += cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out / samples


class Exposure:
    """The camera's auto exposure over a stream of frames (see the module docstring), deterministic in ``seed``:
    ``next(radiance_mean, dt)`` takes the mean grey level the scene gives the next frame at unit exposure and gain,
    ``dt`` s after the one before, and returns (the interval before the next frame, s; its exposure, the share of
    ``exposure_s``; the factor its radiance is multiplied by: the scene's brightness times the camera's gain)."""

    def __init__(self, model: SensorModel, seed: int) -> None:
        self.model = model
        self.rng = np.random.default_rng([seed, 6007])
        mean, sigma, _ = model.brightness
        self.log_light = mean + sigma * float(self.rng.standard_normal())  # the scene's brightness, log units
        self.level = 1.0  # exposure x gain the loop has settled on

    def next(self, radiance_mean: float, dt: float) -> tuple[float, float, float]:
        m = self.model
        mean, sigma, tau = m.brightness
        keep = math.exp(-max(dt, 0.0) / tau)
        self.log_light = mean + keep * (self.log_light - mean) + sigma * math.sqrt(1 - keep**2) * float(
            self.rng.standard_normal())
        seen = max(radiance_mean * math.exp(self.log_light) * self.level, 1e-3)
        self.level = float(np.clip(self.level * (m.target_grey / seen) ** m.ae_lag, 0.05, 16.0))
        exposure = min(self.level, 1.0)  # the exposure takes the level up to the longest one; beyond it, gain
        need = exposure * m.exposure_s
        interval = next((i for i in m.frame_intervals_s if i >= need), m.frame_intervals_s[-1])
        return interval, exposure, self.level / exposure * math.exp(self.log_light)


def finish(radiance: np.ndarray, gain: float, model: SensorModel, rng: np.random.Generator) -> np.ndarray:
    """The stored mono8 frame [H,W] of ``radiance`` [H,W] (grey levels at unit exposure and gain; the exposure already
    applied by the caller) times ``gain``: vignetting, shot and read noise, quantisation, JPEG."""
    H, W = radiance.shape
    img = radiance.astype(np.float32) * np.float32(gain)
    if model.vignetting:
        v, u = np.mgrid[0:H, 0:W].astype(np.float32)
        r2 = ((u - W / 2) ** 2 + (v - H / 2) ** 2) / ((W / 2) ** 2 + (H / 2) ** 2)
        img *= 1.0 - np.float32(model.vignetting) * r2
    if model.shot_noise or model.read_noise:
        sigma = np.sqrt(model.read_noise**2 + model.shot_noise**2 * np.clip(img, 0, 255) / 255.0)
        img = img + sigma * rng.standard_normal(img.shape).astype(np.float32)
    out = np.clip(img + 0.5, 0, 255).astype(np.uint8)
    if model.jpeg_quality:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(model.jpeg_quality)])
        out = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    return out


__all__ = ["REALSENSE", "Exposure", "SensorModel", "blur", "finish"]
