"""Self-calibration of the camera-IMU rig from the backbone's rotations (beyond the paper): the rotation of the camera
mount and the time offset between camera and IMU, estimated online over the clips of a flight.

The backbone's relative rotations between two frames of a clip, carried into the body frame through the camera
mount, must equal the gyro's integrated between the same two instants (the rotation check). A mount off by a
rotation ``delta`` (the true R_BC is Exp(delta) R_BC) turns every body rotation M_ij into Exp(delta) M_ij
Exp(-delta); a camera whose frame at t shows the body at IMU time t + td turns the gyro's rotation R_ij into
Exp(-w_i td) R_ij Exp(w_j td) (w: the bias-corrected body rate at the two frames). To first order the pair residual
r_ij = Log(R_ij^T M_ij) is then

    r_ij = (I - R_ij^T) delta + (w_j - R_ij^T w_i) td - dT_ij dbg + noise,

linear in (delta, td) and in the clip's gyro-bias error dbg (a nuisance, eliminated per clip). A turn about an axis
observes the mount's rotation about the axes across it, a change of rate the offset; hovering, or turning about one
axis only, leaves the rest unobserved, and the estimate says so by its sigma. Each clip's information is added to the
flight's (a linear Gaussian estimate with a random walk between clips, so a slowly changing rig is followed),
linearised at the current estimate; a clip whose rotations the model does not explain (the residual's RMS above
``max_rotation_error`` / 3 after its own fit: a backbone failure) is left out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from vi3_core import so3
from vi3_core.init.gyro_bias import _pair_indices, body_rotations
from vi3_core.preintegration import frame_rotations, merged_grid
from vi3_core.types import Clip, Geometry

MIN_ROTATION_NOISE_RAD = math.radians(0.02)  # no backbone's rotations are trusted as better than this per frame


@dataclass(frozen=True)
class CalibrationOptions:
    """self_calibration: estimate the rig (false: the configured calibration, as given);
    calib_max_rotation_sigma: deg, the estimate of the mount's rotation replaces the configured one once its largest
        1-sigma is below this; calib_max_offset_sigma: s, the same for the time offset;
    calib_prior_rotation: deg, calib_prior_offset: s, how far the configuration may be off (the estimate's prior);
    calib_rotation_walk: deg/sqrt(s), calib_offset_walk: s/sqrt(s), how fast the rig may change in flight."""

    self_calibration: bool = True
    calib_max_rotation_sigma: float = 0.3
    calib_max_offset_sigma: float = 0.002
    calib_prior_rotation: float = 10.0
    calib_prior_offset: float = 0.05
    calib_rotation_walk: float = 0.01
    calib_offset_walk: float = 1e-4

    def __post_init__(self) -> None:
        values = {k: v for k, v in vars(self).items() if k != "self_calibration"}
        bad = [k for k, v in values.items() if not (math.isfinite(v) and v > 0)]
        if bad:
            raise ValueError(f"CalibrationOptions: {', '.join(bad)} must be finite and > 0")


@dataclass(frozen=True)
class RigEstimate:
    """The rig as the flight's rotations show it, relative to the configuration: rotation [3] rad, the mount's
    correction in the body frame (true R_BC = Exp(rotation) R_BC), time_offset s (a frame at camera time t shows the
    body at IMU time t + configured offset + time_offset); cov [4,4] their covariance; clips: how many were used;
    rotation_applied / offset_applied: whether each replaces the configuration (its sigma passed its limit)."""

    rotation: np.ndarray
    time_offset: float
    cov: np.ndarray
    clips: int = 0
    rotation_applied: bool = False
    offset_applied: bool = False

    @property
    def rotation_sigma(self) -> np.ndarray:
        """[3] rad: the 1-sigma of the mount's rotation about each body axis."""
        return np.sqrt(np.maximum(np.diag(self.cov)[:3], 0.0))

    @property
    def time_offset_sigma(self) -> float:
        return math.sqrt(max(float(self.cov[3, 3]), 0.0))

    def describe(self) -> str:
        deg, sd = np.degrees(self.rotation), np.degrees(self.rotation_sigma)
        rot = " ".join(f"{a:+.2f}+-{s:.2f}" for a, s in zip(deg, sd))
        return (f"mount rotation [{rot}] deg ({'applied' if self.rotation_applied else 'configured'}), time offset "
                f"{1e3 * self.time_offset:+.1f}+-{1e3 * self.time_offset_sigma:.1f} ms "
                f"({'applied' if self.offset_applied else 'configured'}), {self.clips} clips")

    def apply(self, clip: Clip) -> Clip:
        """``clip`` with the applied parts of the estimate: its mount turned, its stamps (IMU time) moved by the
        time offset, its IMU cut again from its history for them (the clip as it is where that history is missing)."""
        T_BC = clip.T_BC
        if self.rotation_applied:
            T_BC = T_BC.copy()
            T_BC[:3, :3] = so3.exp(self.rotation) @ clip.T_BC[:3, :3]
        if not self.offset_applied:
            return replace(clip, T_BC=T_BC)
        stamps = clip.stamps + self.time_offset
        history = clip.imu_history
        if history is None or not len(history) or history.t[0] > stamps[0] or history.t[-1] < stamps[-1]:
            return replace(clip, T_BC=T_BC)
        return replace(clip, T_BC=T_BC, stamps=stamps, imu=history.window(float(stamps[0]), float(stamps[-1])))


class RigCalibrator:
    """The flight's estimate of the rig (module docstring): ``add`` each clip the backbone predicted (with the
    configured calibration), ``estimate`` at any time."""

    def __init__(self, options: CalibrationOptions | None = None, *, max_rotation_error_deg: float = 2.0) -> None:
        self.options = options or CalibrationOptions()
        o = self.options
        self._prior = np.diag([math.radians(o.calib_prior_rotation) ** -2] * 3 + [o.calib_prior_offset ** -2])
        self.info = self._prior.copy()  # information of x = (delta [3], td)
        self.x = np.zeros(4)
        self.clips = 0
        self.t_last: float | None = None
        self.max_noise = math.radians(max_rotation_error_deg) / 3.0

    @property
    def estimate(self) -> RigEstimate:
        cov = np.linalg.inv(self.info)
        est = RigEstimate(self.x[:3].copy(), float(self.x[3]), cov, self.clips)
        o = self.options
        return replace(est, rotation_applied=bool(o.self_calibration and est.rotation_sigma.max()
                                                   < math.radians(o.calib_max_rotation_sigma)),
                       offset_applied=bool(o.self_calibration and est.time_offset_sigma < o.calib_max_offset_sigma))

    def add(self, clip: Clip, geometry: Geometry, bg: np.ndarray) -> str:
        """Take clip's rotations (``geometry``: its prediction, with the configured mount ``clip.T_BC`` and stamps in
        configured IMU time; bg [3] rad/s the stream's gyro bias, the nuisance's linearisation point); "" when they
        were used, else why not."""
        t = float(clip.stamps[0])
        if self.t_last is not None and t > self.t_last:  # the random walk since the last clip
            o = self.options
            walk = np.diag([math.radians(o.calib_rotation_walk) ** 2] * 3 + [o.calib_offset_walk ** 2])
            self.info = np.linalg.inv(np.linalg.inv(self.info) + walk * (t - self.t_last))
        self.t_last = max(t, self.t_last or t)
        got = self._clip_information(clip, geometry, bg)
        if isinstance(got, str):
            return got
        info, step = got
        self.x = np.linalg.solve(self.info + info, self.info @ self.x + info @ (self.x + step))
        self.info = self.info + info
        self.clips += 1
        return ""

    def _clip_information(self, clip: Clip, geometry: Geometry, bg: np.ndarray) -> tuple[np.ndarray, np.ndarray] | str:
        """(information [4,4] of the clip about (delta, td) with its gyro-bias error eliminated, the step [4] from the
        current estimate it points to), or why the clip says nothing."""
        delta, td = self.x[:3], float(self.x[3])
        T_BC = clip.T_BC.copy()
        T_BC[:3, :3] = so3.exp(delta) @ clip.T_BC[:3, :3]
        stamps = clip.stamps + td
        imu = clip.imu_history if clip.imu_history is not None else clip.imu
        if not len(imu) or imu.t[0] > stamps[0] or imu.t[-1] < stamps[-1]:
            return "no IMU at the frames' times"
        grid = merged_grid(imu.window(float(stamps[0]), float(stamps[-1])), stamps)
        R = frame_rotations(grid, bg)
        w = grid.gyro[grid.frame_idx] - bg  # body rates at the frames
        M = body_rotations(geometry.T_wc[:, :3, :3], T_BC)
        i, j = _pair_indices(len(stamps))
        R_ij = np.swapaxes(R[i], 1, 2) @ R[j]
        r = so3.log(np.swapaxes(R_ij, 1, 2) @ np.swapaxes(M[i], 1, 2) @ M[j])  # [P,3]
        H = np.zeros((len(i), 3, 7))
        R_ijT = np.swapaxes(R_ij, 1, 2)
        H[:, :, 0:3] = np.eye(3) - R_ijT
        H[:, :, 3] = w[j] - (R_ijT @ w[i][:, :, None])[:, :, 0]
        H[:, :, 4:7] = -(stamps[j] - stamps[i])[:, None, None] * np.eye(3)
        H, r = H.reshape(-1, 7), r.reshape(-1)
        sol, *_ = np.linalg.lstsq(H, r, rcond=None)
        dof = len(r) - 7
        noise = math.sqrt(float(((r - H @ sol) ** 2).sum()) / max(dof, 1) / 2.0)  # per frame: a pair has two
        if noise > self.max_noise:
            return (f"rotations not explained by the rig ({math.degrees(noise):.2f} deg per frame after the fit): a "
                    "backbone failure")
        # the pairs share frames: as many independent ones as intervals
        var = 2.0 * max(noise, MIN_ROTATION_NOISE_RAD) ** 2 * (len(i) / (len(stamps) - 1))
        info = H.T @ H / var
        keep, drop = slice(0, 4), slice(4, 7)
        info_m = info[keep, keep] - info[keep, drop] @ np.linalg.pinv(info[drop, drop]) @ info[drop, keep]
        return 0.5 * (info_m + info_m.T), sol[:4]


__all__ = ["CalibrationOptions", "RigCalibrator", "RigEstimate"]
