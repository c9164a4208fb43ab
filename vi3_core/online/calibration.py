"""Self-calibration of the camera-IMU rig from the backbone's rotations (beyond the paper): the rotation of the camera
mount and the time offset between camera and IMU, estimated online over the clips of a flight.

The backbone's relative rotations between two frames of a clip, carried into the body frame through the camera
mount, must equal the gyro's integrated between the same two instants (the rotation check). A mount off by a
rotation ``delta`` (the true R_BC is Exp(delta) R_BC) turns every body rotation M_ij into Exp(delta) M_ij
Exp(-delta); a camera whose frame at t shows the body at IMU time t + td turns the gyro's rotation R_ij into
Exp(-w_i td) R_ij Exp(w_j td) (w: the bias-corrected body rate at the two frames). To first order the pair residual
r_ij = Log(R_ij^T M_ij) is then

    r_ij = (I - R_ij^T) delta + (w_j - R_ij^T w_i) td - R_j^T (phi_j - phi_i) dbg + noise,

linear in (delta, td) and in the clip's gyro-bias error dbg (phi_k: the preintegration's bias Jacobian of R_B1Bk; a
nuisance, eliminated per clip). A turn about an axis observes the mount's rotation about the axes across it, a change
of rate the offset; hovering, or turning about one axis only, leaves the rest unobserved, and the estimate says so by
its sigma. The pairs share frames, so they are weighed by their covariance (``_pair_weights``), and each clip's noise
is what its residuals show. Each clip's information is added to the flight's (a Gaussian estimate with a random walk
between clips, so a slowly changing rig is followed) in an iterated update, the clip's residuals relinearised at the
updated estimate (so that a configuration far off is not locked in by the first clips' linearisation); a clip whose
rotations the model does not explain (the residual's RMS above ``max_rotation_error`` / 3 after its own fit: a
backbone failure) is left out. A part of the estimate replaces the configuration once its sigma is below its limit
and it differs from the configuration significantly (99 %): a configuration the flight cannot tell from the estimate
is kept, since replacing a good calibration by an estimate of a few tenths of a degree would make it worse.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, replace

import numpy as np

from vi3_core import so3
from vi3_core.init.gyro_bias import _pair_indices, body_rotations
from vi3_core.preintegration import preintegrate
from vi3_core.types import Clip, Geometry, ImuSamples

MIN_ROTATION_NOISE_RAD = math.radians(0.02)  # no backbone's rotations are trusted as better than this per frame
#: chi-square quantiles at 99 % for 3 and 1 degrees of freedom: an estimate replaces the configuration only where it
#: differs from it this significantly (a configuration the flight cannot tell from the estimate is kept)
CHI2_99 = {3: 11.345, 1: 6.635}
RELINEARISATIONS = 3  # Gauss-Newton steps of each clip's update: a first guess far off is not locked in
RATE_HALF_WIDTH_S = 0.025  # s; the body rate at a frame is the gyro's mean over +-this (10 samples at 200 Hz)


@dataclass(frozen=True)
class CalibrationOptions:
    """self_calibration: estimate the rig (false: the configured calibration, as given);
    calib_max_rotation_sigma: deg, the estimate of the mount's rotation replaces the configured one once its largest
        1-sigma is below this (and it is significantly off the configuration); calib_max_offset_sigma: s, the same for
        the time offset;
    calib_prior_rotation: deg, calib_prior_offset: s, how far the configuration may be off (the estimate's prior);
    calib_rotation_walk: deg/sqrt(s), calib_offset_walk: s/sqrt(s), how fast the rig may change in flight;
    calib_tolerance_rotation: deg, calib_tolerance_offset: s, how far the configuration may be off before the node
        warns (``RigEstimate.off_by``: beyond this by three sigmas)."""

    self_calibration: bool = True
    calib_max_rotation_sigma: float = 0.3
    calib_max_offset_sigma: float = 0.002
    calib_prior_rotation: float = 10.0
    calib_prior_offset: float = 0.03
    calib_rotation_walk: float = 0.01
    calib_offset_walk: float = 1e-4
    calib_tolerance_rotation: float = 0.5
    calib_tolerance_offset: float = 0.005

    def __post_init__(self) -> None:
        values = {k: v for k, v in vars(self).items() if k != "self_calibration"}
        bad = [k for k, v in values.items() if not (math.isfinite(v) and (v >= 0 if "tolerance" in k else v > 0))]
        if bad:
            raise ValueError(f"CalibrationOptions: {', '.join(bad)} must be finite and > 0 (tolerances >= 0)")


@dataclass(frozen=True)
class RigEstimate:
    """The rig as the flight's rotations show it, relative to the configuration: rotation [3] rad, the mount's
    correction in the body frame (true R_BC = Exp(rotation) R_BC), time_offset s (a frame at camera time t shows the
    body at IMU time t + configured offset + time_offset); cov [4,4] their covariance; clips: how many were used;
    rotation_applied / offset_applied: whether each part replaces the configuration (``RigCalibrator``: self-calibration
    on, its sigma below its limit in ``options`` and the estimate significantly off the configuration, at some clip of
    the flight)."""

    rotation: np.ndarray
    time_offset: float
    cov: np.ndarray
    clips: int = 0
    rotation_applied: bool = False
    offset_applied: bool = False
    options: CalibrationOptions = field(default_factory=CalibrationOptions)

    @property
    def rotation_sigma(self) -> np.ndarray:
        """[3] rad: the 1-sigma of the mount's rotation about each body axis."""
        return np.sqrt(np.maximum(np.diag(self.cov)[:3], 0.0))

    @property
    def time_offset_sigma(self) -> float:
        return math.sqrt(max(float(self.cov[3, 3]), 0.0))

    @property
    def rotation_observed(self) -> np.ndarray:
        """[3] bool: whether the mount's rotation about each body axis is known well enough to be applied."""
        return self.rotation_sigma < math.radians(self.options.calib_max_rotation_sigma)

    @property
    def offset_observed(self) -> bool:
        return self.time_offset_sigma < self.options.calib_max_offset_sigma

    @property
    def rotation_significant(self) -> bool:
        """Whether the mount's rotation differs from the configuration beyond its uncertainty (chi-square, 99 %)."""
        d = self.rotation
        return float(d @ np.linalg.solve(self.cov[:3, :3], d)) > CHI2_99[3]

    @property
    def offset_significant(self) -> bool:
        return self.time_offset**2 > CHI2_99[1] * float(self.cov[3, 3])

    def describe(self) -> str:
        """One line: the estimate with its sigmas, whether each part is applied and, where not, about which body axes
        the mount's rotation is not observed yet (the flight has not turned across them)."""
        deg, sd = np.degrees(self.rotation), np.degrees(self.rotation_sigma)
        rot = " ".join(f"{a:+.2f}+-{s:.2f}" for a, s in zip(deg, sd))
        unobserved = [axis for axis, seen in zip("xyz", self.rotation_observed) if not seen]
        state = "applied" if self.rotation_applied else (
            f"configured; unobserved about body {','.join(unobserved)}" if unobserved else "configured; agrees")
        offset = "applied" if self.offset_applied else (
            "configured; agrees" if self.offset_observed else "configured; unobserved")
        return (f"mount rotation [{rot}] deg ({state}), time offset {1e3 * self.time_offset:+.1f}+-"
                f"{1e3 * self.time_offset_sigma:.1f} ms ({offset}), {self.clips} clips")

    def as_dict(self) -> dict:
        """JSON-ready: the rotation about the body axes and its sigmas in deg, the time offset and its sigma in ms,
        whether each is applied, the clips used."""
        return {"rotation_deg": np.degrees(self.rotation).tolist(),
                "rotation_sigma_deg": np.degrees(self.rotation_sigma).tolist(),
                "time_offset_ms": 1e3 * self.time_offset, "time_offset_sigma_ms": 1e3 * self.time_offset_sigma,
                "rotation_applied": self.rotation_applied, "offset_applied": self.offset_applied, "clips": self.clips}

    def off_by(self) -> str:
        """How the configuration is off where the estimate is sure it is off by more than its tolerance (by three
        sigmas; ``options.calib_tolerance_*``), "" where it is not: the warning a flight stack's operator needs."""
        o, parts = self.options, []
        angle, sigma = float(np.linalg.norm(self.rotation)), float(self.rotation_sigma.max())
        if angle - 3.0 * sigma > math.radians(o.calib_tolerance_rotation):
            parts.append(f"the camera mount by {math.degrees(angle):.2f} deg (+-{math.degrees(sigma):.2f})")
        sigma = self.time_offset_sigma
        if abs(self.time_offset) - 3.0 * sigma > o.calib_tolerance_offset:
            parts.append(f"the camera-IMU time offset by {1e3 * self.time_offset:+.1f} ms (+-{1e3 * sigma:.1f})")
        return " and ".join(parts)

    def for_clip(self, clip: Clip) -> RigEstimate:
        """The estimate as it can be applied to ``clip``: the time offset only where the clip's IMU history covers its
        frames at their moved times (else the clip keeps its IMU as configured)."""
        if not self.offset_applied:
            return self
        stamps, history = clip.stamps + self.time_offset, clip.imu_history
        if history is None or not len(history) or history.t[0] > stamps[0] or history.t[-1] < stamps[-1]:
            return replace(self, offset_applied=False)
        return self

    def apply(self, clip: Clip) -> Clip:
        """``clip`` with the applied parts of the estimate (``for_clip`` says which it can take): its mount turned;
        its IMU history moved onto the frames' clock by the time offset (a frame at stamp t shows the body at IMU time
        t + time_offset) and its IMU cut again from it. The frames' stamps stay: a frame shared by two clips keeps one
        stamp while the estimate moves."""
        T_BC = so3.turn_T(clip.T_BC, self.rotation) if self.rotation_applied else clip.T_BC
        if not self.offset_applied:
            return replace(clip, T_BC=T_BC)
        history = clip.imu_history.shifted(-self.time_offset)
        return replace(clip, T_BC=T_BC, imu=history.window(float(clip.stamps[0]), float(clip.stamps[-1])),
                       imu_history=history, imu_shift=clip.imu_shift - self.time_offset)

    def corrected(self, T_BC: np.ndarray, time_offset: float) -> tuple[np.ndarray, float]:
        """The configured mount T_BC [4,4] and time offset (s, t_imu = t_cam + time_offset) corrected by the parts of
        the estimate that are sure enough to be applied (the rest as configured): what the calibration file should
        say."""
        T = so3.turn_T(T_BC, self.rotation) if self.rotation_applied else np.array(T_BC, np.float64, copy=True)
        return T, time_offset + (self.time_offset if self.offset_applied else 0.0)


def frame_rates(imu: ImuSamples, stamps: np.ndarray, half_width: float = RATE_HALF_WIDTH_S) -> np.ndarray:
    """[n,3] rad/s: the raw gyro averaged over +-half_width s around each stamp [n] (at least the nearest sample).
    The offset's column of the pair residual is linear in these rates; a single sample's noise in it would bias the
    offset towards zero and overstate its information (errors in variables), most where the body barely turns."""
    t = imu.t
    cs = np.concatenate([np.zeros((1, 3)), np.cumsum(imu.gyro, axis=0)])
    lo = np.searchsorted(t, stamps - half_width, side="left")
    hi = np.maximum(np.searchsorted(t, stamps + half_width, side="right"), lo + 1)
    lo, hi = np.minimum(lo, len(t) - 1), np.minimum(hi, len(t))
    return (cs[hi] - cs[lo]) / (hi - lo)[:, None]


@functools.lru_cache(maxsize=8)
def _pair_weights(n: int) -> np.ndarray:
    """[P,P] the weights of the n frames' pair residuals (pairs as ``_pair_indices``): each frame's rotation error
    enters every pair it is in, so the pairs' covariance is sigma^2 D D^T (D [P,n] the pairs' incidence: -1 at i,
    +1 at j) and its pseudo-inverse weighs them (generalised least squares, n - 1 independent pairs' worth)."""
    i, j = _pair_indices(n)
    D = np.zeros((len(i), n))
    D[np.arange(len(i)), i], D[np.arange(len(i)), j] = -1.0, 1.0
    # D D^T's nonzero eigenvalues are all n; its zero ones come out as rounding (up to 1e-13), which the default cutoff
    # (1e-15 of the largest) inverted into weights of 1e13 for clips of 19 frames and more
    W = np.linalg.pinv(D @ D.T, rcond=1e-10)
    W.flags.writeable = False
    return W


class RigCalibrator:
    """The flight's estimate of the rig (module docstring): ``add`` each clip the backbone predicted (with the
    configured calibration), ``estimate`` at any time."""

    def __init__(self, options: CalibrationOptions | None = None, *, max_rotation_error_deg: float = 2.0) -> None:
        self.options = options or CalibrationOptions()
        o = self.options
        # information of x = (delta [3], td): the prior's, then the flight's
        self.info = np.diag([math.radians(o.calib_prior_rotation) ** -2] * 3 + [o.calib_prior_offset ** -2])
        # the random walk's variance per second between clips
        self._walk = np.diag([math.radians(o.calib_rotation_walk) ** 2] * 3 + [o.calib_offset_walk ** 2])
        self.x = np.zeros(4)
        self.clips = 0
        self.t_last: float | None = None
        self.max_noise = math.radians(max_rotation_error_deg) / 3.0
        self._rotation_on = self._offset_on = False

    @property
    def estimate(self) -> RigEstimate:
        return RigEstimate(self.x[:3].copy(), float(self.x[3]), np.linalg.inv(self.info), self.clips,
                           self._rotation_on, self._offset_on, self.options)

    def _decide(self) -> None:
        """Each part replaces the configuration once the estimate is sure of it (its sigma below its limit) and sure
        that the configuration is off (significantly); from then on it stays replaced, following the estimate."""
        if not self.options.self_calibration:
            return
        est = self.estimate
        self._rotation_on |= bool(est.rotation_observed.all() and est.rotation_significant)
        self._offset_on |= bool(est.offset_observed and est.offset_significant)

    def add(self, clip: Clip, geometry: Geometry, bg: np.ndarray) -> str:
        """Take clip's rotations (``geometry``: its prediction, with the configured mount ``clip.T_BC`` and stamps in
        configured IMU time; bg [3] rad/s the stream's gyro bias, the nuisance's linearisation point); "" when they
        were used, else why not."""
        t = float(clip.stamps[0])
        if self.t_last is not None and t > self.t_last:  # the random walk since the last clip
            self.info = np.linalg.inv(np.linalg.inv(self.info) + self._walk * (t - self.t_last))
        self.t_last = max(t, self.t_last or t)
        x, linearised = self.x, False
        for _ in range(RELINEARISATIONS):  # Gauss-Newton on the prior and the clip (an iterated Kalman update)
            got = self._clip_information(clip, geometry, bg, x)
            if isinstance(got, str):
                if not linearised:
                    return got
                break  # the step moved the frames past the clip's IMU: keep the last linearisation
            linearised, (info, step) = True, got
            x = np.linalg.solve(self.info + info, self.info @ self.x + info @ (x + step))
        self.x, self.info = x, self.info + info
        self.clips += 1
        self._decide()
        return ""

    def _clip_information(self, clip: Clip, geometry: Geometry, bg: np.ndarray,
                          x: np.ndarray) -> tuple[np.ndarray, np.ndarray] | str:
        """(information [4,4] of the clip about (delta, td) with its gyro-bias error eliminated, the step [4] from
        ``x`` [4] (where the residuals are linearised) that the clip alone points to), or why the clip says
        nothing."""
        delta, td = x[:3], float(x[3])
        T_BC = so3.turn_T(clip.T_BC, delta)
        stamps = clip.stamps + td
        imu = clip.imu_history if clip.imu_history is not None else clip.imu
        if not len(imu) or imu.t[0] > stamps[0] or imu.t[-1] < stamps[-1]:
            return "no IMU at the frames' times"
        dof = 3 * (len(stamps) - 1) - 7
        if dof < 3:
            return f"{len(stamps)} frames are too few to tell the rig from the clip's gyro bias"
        pre = preintegrate(imu.window(float(stamps[0]), float(stamps[-1])), stamps, bg, jacobians=True)
        R, phi = pre.R, pre.J.phi_bg  # R_B1Bk(bg + d) = Exp(phi_k d) R_B1Bk(bg)
        w = frame_rates(imu, stamps) - bg
        M = body_rotations(geometry.T_wc[:, :3, :3], T_BC)
        i, j = _pair_indices(len(stamps))
        R_ij = np.swapaxes(R[i], 1, 2) @ R[j]
        r = so3.log(np.swapaxes(R_ij, 1, 2) @ np.swapaxes(M[i], 1, 2) @ M[j])  # [P,3]
        H = np.zeros((len(i), 3, 7))
        R_ijT = np.swapaxes(R_ij, 1, 2)
        H[:, :, 0:3] = np.eye(3) - R_ijT
        H[:, :, 3] = w[j] - (R_ijT @ w[i][:, :, None])[:, :, 0]
        H[:, :, 4:7] = -np.swapaxes(R[j], 1, 2) @ (phi[j] - phi[i])
        W = _pair_weights(len(stamps))
        info = np.einsum("pak,pq,qal->kl", H, W, H)
        sol = np.linalg.lstsq(info, np.einsum("pak,pq,qa->k", H, W, r), rcond=None)[0]
        res = r - H @ sol
        # rad per frame and axis (W is positive semi-definite: a form a rounding error below 0 is 0)
        noise = math.sqrt(max(float(np.einsum("pa,pq,qa->", res, W, res)), 0.0) / dof)
        if noise > self.max_noise:
            return (f"rotations not explained by the rig ({math.degrees(noise):.2f} deg per frame after the fit): a "
                    "backbone failure")
        # the noise is estimated from the clip itself: its information is worth dof / (dof - 2) less on average
        info = info / (max(noise, MIN_ROTATION_NOISE_RAD) ** 2 * dof / (dof - 2))
        keep, drop = slice(0, 4), slice(4, 7)
        info_m = info[keep, keep] - info[keep, drop] @ np.linalg.pinv(info[drop, drop]) @ info[drop, keep]
        return 0.5 * (info_m + info_m.T), sol[:4]


__all__ = ["CalibrationOptions", "RigCalibrator", "RigEstimate"]
