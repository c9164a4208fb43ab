"""``OnlineEstimator``: metric state carried across the clips of a stream (beyond the paper, which treats every clip
on its own), and the chaining of the clips into one continuous odom trajectory.

Per clip: (1) the priors are the previous clip's state at its frame nearest before this clip's first frame,
propagated to that frame through the IMU bridge (``preintegrate`` with the filtered gyro bias): the attitude R_OB1
(hence gravity in B1, g_B1 = R_OB1^T g_O), the velocity v1 and the gyro bias; (2) the clip's own GT-free
initialisation runs as always; (3) each prior is tested against it: gravity by angle, velocity by the position
residual and the scale it implies (``fit_positions``); (4) with the priors that pass, scale and v1 come from a
position fit (well conditioned) rather than from velocity increments. A prior that fails is dropped for the clip,
and the reason is reported in ``InitResult.diagnostics["online"]``. With no state, after a gap longer than
``max_gap_s``, without IMU over the bridge, for a clip whose data is rejected or after a clip that could not be
placed, the state is reset: the clip takes the
GT-free initialisation, and is placed in odom at the IMU-propagated (or, without IMU over the gap, the last) pose,
re-levelled with the clip's own gravity, yaw kept.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from vi3_core import so3
from vi3_core.init import InitOptions, initialise_clip, validate
from vi3_core.init.position_fit import fit_positions
from vi3_core.online.chain import ChainedClip, Trajectory, gravity_align
from vi3_core.online.options import OnlineOptions
from vi3_core.preintegration import preintegrate
from vi3_core.types import AnchorResult, Clip, Geometry, ImuSamples, InitResult, InitStatus


@dataclass(frozen=True)
class OdomState:
    """The last chained clip: stamps [n] s, T_OB [n,4,4] body poses in odom, v_O [n,3] m/s, bg [3] rad/s filtered
    gyro bias."""

    stamps: np.ndarray
    T_OB: np.ndarray
    v_O: np.ndarray
    bg: np.ndarray


@dataclass(frozen=True)
class Placement:
    """Where the next clip's first body frame goes: R_OB1 [3,3], p_OB1 [3] m; ``level``: re-level R_OB1 with the
    clip's adopted gravity (False when the clip's own gravity was rejected against a trusted prior)."""

    R_OB1: np.ndarray
    p_OB1: np.ndarray
    level: bool


@dataclass
class OnlineDecision:
    """What the estimator did with a clip: priors used ("g", "v1", "bg"), rejected priors {name: reason},
    reset reason ("" when none)."""

    used: tuple[str, ...] = ()
    rejected: dict[str, str] | None = None
    reset: str = ""

    def describe(self) -> str:
        parts = [f"priors: {','.join(self.used) or 'none'}"]
        parts += [f"{name} prior rejected: {why}" for name, why in sorted((self.rejected or {}).items())]
        if self.reset:
            parts.append(f"reset: {self.reset}")
        return "; ".join(parts)


def _merge_imu(a: ImuSamples | None, b: ImuSamples | None) -> ImuSamples | None:
    parts = [p for p in (a, b) if p is not None and len(p)]
    if not parts:
        return None
    imu = ImuSamples.concatenate([replace(p, orientation=None) for p in parts])
    _, idx = np.unique(imu.t, return_index=True)  # sorted, first occurrence of each stamp
    return imu.select(idx)


class OnlineEstimator:
    """Priors from the stream for each clip's initialisation, and the odom trajectory of the chained clips.

    Usage per clip: ``init = est.initialise(clip, geometry)`` (or as ``anchor(..., init=lambda g:
    est.initialise(clip, g))``), then ``est.update(clip, anchor_result)`` -> ChainedClip or None. Deterministic:
    the same clips give the same output. ``state`` may be replaced between clips (tests inject a wrong prior)."""

    def __init__(self, *, options: OnlineOptions | None = None, init_options: InitOptions | None = None) -> None:
        self.options = options or OnlineOptions()
        self.init_options = init_options or InitOptions()
        self.state: OdomState | None = None
        self.trajectory = Trajectory()
        self.last: OnlineDecision = OnlineDecision()
        self._imu: ImuSamples | None = None
        self._pending: tuple[float, Placement] | None = None
        self._reset_reason = "no state yet (first clip)"

    @property
    def g_O(self) -> np.ndarray:
        return np.array([0.0, 0.0, -self.init_options.gravity_norm])

    # ---- priors ---------------------------------------------------------------------------------------------

    def _remember_imu(self, clip: Clip) -> None:
        imu = _merge_imu(_merge_imu(self._imu, clip.imu_history), clip.imu)
        keep = imu.t >= imu.t[-1] - self.options.imu_keep_s
        self._imu = imu.select(keep)

    def _bridge(self, t1: float, max_gap_s: float) -> tuple[Placement, np.ndarray] | str:
        """The previous state propagated to t1 through at most ``max_gap_s`` s: (placement, v_O at t1), or why it
        cannot be."""
        st = self.state
        k = int(np.searchsorted(st.stamps, t1 + 1e-9, side="right")) - 1
        if k < 0:
            return f"clip starts at {t1:.3f} s, before the previous clip's first frame"
        gap = t1 - float(st.stamps[k])
        if gap > max_gap_s:
            return f"gap of {gap:.2f} s > max_gap_s {max_gap_s} s"
        R_k, p_k, v_k = st.T_OB[k, :3, :3], st.T_OB[k, :3, 3], st.v_O[k]
        if gap < 1e-9:
            return Placement(R_k, p_k, True), v_k
        stamps = np.array([st.stamps[k], t1])
        why = validate.check_imu(self._imu, stamps, self.init_options) if self._imu is not None else "no IMU"
        if why:
            return f"no IMU over the {gap:.2f} s bridge: {why}"
        pre = preintegrate(self._imu.window(stamps[0], stamps[1]), stamps, st.bg)
        g, dt = self.g_O, gap
        # Eqs. preintegrationRotation / Velocity / Translation over the bridge, in odom.
        R1 = R_k @ pre.R[1]
        v1 = v_k + g * dt + R_k @ pre.beta[1]
        p1 = p_k + v_k * dt + 0.5 * g * dt**2 + R_k @ pre.alpha[1]
        return Placement(R1, p1, True), v1

    def _reset(self, clip: Clip, free: InitResult, why: str) -> InitResult:
        """The GT-free result, placed at the IMU-bridged (or the last) pose, re-levelled with the clip's gravity
        (yaw kept)."""
        if self.state is None:
            place = Placement(np.eye(3), np.zeros(3), True)
        else:
            bridged = self._bridge(float(clip.stamps[0]), math.inf)
            place = bridged[0] if not isinstance(bridged, str) else Placement(self.state.T_OB[-1, :3, :3],
                                                                              self.state.T_OB[-1, :3, 3], True)
        self._pending = (float(clip.stamps[0]), place)
        self._reset_reason = why
        self.last = OnlineDecision(reset=why)
        free.diagnostics["online"] = self.last.describe()
        return free

    def initialise(self, clip: Clip, geometry: Geometry) -> InitResult:
        """The clip's InitResult: the GT-free one, or one built on the priors that pass their tests."""
        o = self.options
        self._remember_imu(clip)
        free = initialise_clip(clip, geometry, options=self.init_options)
        if self.state is None or self._reset_reason:
            return self._reset(clip, free, self._reset_reason or "no state")
        if free.status is InitStatus.REJECTED:
            return self._reset(clip, free, f"clip rejected ({free.reason})")
        bridged = self._bridge(float(clip.stamps[0]), o.max_gap_s)
        if isinstance(bridged, str):
            return self._reset(clip, free, bridged)
        place, v_O1 = bridged
        g_prior = place.R_OB1.T @ self.g_O
        v1_prior = place.R_OB1.T @ v_O1
        rejected: dict[str, str] = {}

        # Gravity: the prior is kept unless the positions fit clearly worse with it than with the clip's own gravity
        # (a noisy clip's own gravity can be off by many degrees, so the angle alone is only a loose cap).
        bg = (1.0 - o.bg_gain) * self.state.bg + o.bg_gain * free.bg
        pre = preintegrate(clip.imu, clip.stamps, bg)
        angle = math.degrees(float(so3.angle_between(g_prior, free.g))) if np.isfinite(free.g).all() else 0.0
        fit_g_prior = fit_positions(geometry.T_wc, pre, clip.T_BC, g_prior)
        fit_g_free = fit_positions(geometry.T_wc, pre, clip.T_BC, free.g) if angle > 0.0 else fit_g_prior
        limit_g = max(o.residual_ratio * fit_g_free.rms, o.residual_floor_m)
        if angle > o.gravity_tol_deg:
            rejected["g"] = f"{angle:.1f} deg from the clip's own gravity > {o.gravity_tol_deg} deg"
        elif not fit_g_prior.rms <= limit_g:
            rejected["g"] = f"position residual {fit_g_prior.rms:.3f} m > {limit_g:.3f} m with the clip's own gravity"
        if "g" in rejected:
            rejected["v1"] = "needs the gravity prior"
            self._pending = (float(clip.stamps[0]), replace(place, level=False))
            self.last = OnlineDecision(used=(), rejected=rejected)
            free.diagnostics["online"] = self.last.describe()
            return free

        g = (1.0 - o.gravity_gain) * g_prior + o.gravity_gain * free.g if free.ok else g_prior
        g = self.init_options.gravity_norm * g / np.linalg.norm(g)
        # Velocity: its position residual against the free (s, v1) fit, and the scale each implies.
        fit_free = fit_positions(geometry.T_wc, pre, clip.T_BC, g)
        fit_prior = fit_positions(geometry.T_wc, pre, clip.T_BC, g, v1=v1_prior)
        limit = max(o.residual_ratio * fit_free.rms, o.residual_floor_m)
        used = ["g", "bg"]
        if not fit_prior.rms <= limit:
            rejected["v1"] = f"position residual {fit_prior.rms:.3f} m > {limit:.3f} m"
        elif not 1.0 / o.scale_ratio <= fit_prior.scale / fit_free.scale <= o.scale_ratio:
            rejected["v1"] = f"implied scale {fit_prior.scale:.3g} vs the clip's own {fit_free.scale:.3g}"
        if "v1" in rejected:
            fit = fit_free
        else:
            fit = fit_positions(geometry.T_wc, pre, clip.T_BC, g, v1_prior=v1_prior, v1_weight_s=o.v1_weight_s)
            used.insert(1, "v1")
        if not fit.scale > 0.0:
            return self._reset(clip, free, f"position fit gives scale {fit.scale:.3g}")
        self._pending = (float(clip.stamps[0]), place)
        self.last = OnlineDecision(used=tuple(used), rejected=rejected)
        diag = dict(free.diagnostics, online=self.last.describe(), free_status=free.status.value,
                    free_scale=free.scale, free_g=free.g, prior_g_angle_deg=angle, prior_rms=fit_prior.rms,
                    free_rms=fit_free.rms)
        return InitResult(InitStatus.OK, "ok (online priors)", bg=bg, g=g, scale=fit.scale, v1=fit.v1,
                          gravity_source="online", target=pre.propagate(g, fit.v1, clip.T_BC),
                          diagnostics=diag)

    # ---- chaining -------------------------------------------------------------------------------------------

    def update(self, clip: Clip, result: AnchorResult) -> ChainedClip | None:
        """Place the anchored clip in odom and make it the state for the next clip. A clip that is not ok (or
        that ``initialise`` did not see) is not placed, and the next clip resets."""
        init = result.init
        target = result.target or init.target
        if not init.ok or target is None or result.mode == "none" or self._pending is None \
                or self._pending[0] != float(clip.stamps[0]):
            self._reset_reason = f"previous clip not placed ({init.status.value}: {init.reason})"
            self._pending = None
            return None
        place = self._pending[1]
        self._pending = None
        R_OB1 = gravity_align(place.R_OB1, init.g) if place.level else place.R_OB1
        T_BC = clip.T_BC
        T_B1B = T_BC @ result.geometry.T_wc @ so3.inv_T(T_BC)  # metric body poses in B1
        T_OB = so3.make_T(R_OB1, place.p_OB1) @ T_B1B
        v_O = target.v @ R_OB1.T
        if self._reset_reason and self.state is not None:
            self.trajectory.resets.append(float(clip.stamps[0]))
        self._reset_reason = ""
        self.state = OdomState(np.asarray(clip.stamps, dtype=np.float64), T_OB, v_O, np.asarray(init.bg))
        chained = ChainedClip(self.state.stamps, T_OB, v_O)
        self.trajectory.extend(chained)
        return chained
