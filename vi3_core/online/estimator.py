"""``OnlineEstimator``: metric state carried across the clips of a stream (beyond the paper, which treats every clip
on its own), and the chaining of the clips into one continuous odom trajectory.

Per clip: (1) the clip's own GT-free initialisation runs as always (its gyro bias and its data checks); (2) the clip
joins a window of the clips of the last ``window_s`` seconds, fitted jointly (``window.WindowSystem``: gravity and
accelerometer bias shared, one scale and first-frame velocity per clip, velocities tied through the IMU); a clip
whose positions do not fit the window is rejected and named; (3) the odom state's gravity and velocity at the
clip's first frame, propagated through the IMU bridge, are priors of that fit, each dropped (and named) when it
disagrees with the window's own estimate; (4) the clip's scale, gravity and v1 come from the window. The gyro bias
is the median of the own estimates of the clips of the last ``bg_window_s`` seconds. After a gap longer than
``max_gap_s``, without IMU over the window, for a clip whose data is rejected, or after ``max_rejects``
inconsistent clips in a row, the window restarts from the current clip, which takes the GT-free initialisation.
Every clip is placed in odom at its IMU-propagated pose (the last pose without IMU), levelled with its adopted
gravity, yaw kept.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from vi3_core import so3
from vi3_core.init import InitOptions, initialise_clip, validate
from vi3_core.online.chain import ChainedClip, Trajectory, gravity_align
from vi3_core.online.options import OnlineOptions
from vi3_core.online.window import WindowClip, WindowSystem
from vi3_core.preintegration import preintegrate
from vi3_core.types import AnchorResult, Clip, Geometry, ImuSamples, InitResult, InitStatus


@dataclass(frozen=True)
class OdomState:
    """The last chained clip: stamps [n] s, T_OB [n,4,4] body poses in odom, v_O [n,3] m/s, bg [3] rad/s gyro
    bias."""

    stamps: np.ndarray
    T_OB: np.ndarray
    v_O: np.ndarray
    bg: np.ndarray


@dataclass(frozen=True)
class Placement:
    """Where the next clip's first body frame goes: R_OB1 [3,3], p_OB1 [3] m (re-levelled with the clip's adopted
    gravity when it is chained)."""

    R_OB1: np.ndarray
    p_OB1: np.ndarray


@dataclass
class OnlineDecision:
    """What the estimator did with a clip: window size (clips fitted jointly, 0: none), priors used ("g", "v1"),
    rejected {name: reason} ("clip": the clip itself against the window), reset reason ("" when none)."""

    window: int = 0
    used: tuple[str, ...] = ()
    rejected: dict[str, str] = field(default_factory=dict)
    reset: str = ""

    def describe(self) -> str:
        parts = [f"window {self.window} clips; priors: {','.join(self.used) or 'none'}"]
        parts += [f"{name} {'prior ' if name != 'clip' else ''}rejected: {why}"
                  for name, why in sorted(self.rejected.items())]
        if self.reset:
            parts.append(f"reset: {self.reset}")
        return "; ".join(parts)


def _merge_imu(a: ImuSamples | None, b: ImuSamples | None) -> ImuSamples | None:
    """Both sample sets, sorted, each stamp once, non-finite samples dropped (a gap they leave is caught later)."""
    parts = [p for p in (a, b) if p is not None and len(p)]
    if not parts:
        return None
    imu = ImuSamples.concatenate([replace(p, orientation=None) for p in parts])
    finite = np.isfinite(imu.t) & np.isfinite(imu.gyro).all(1) & np.isfinite(imu.accel).all(1)
    imu = imu.select(np.flatnonzero(finite))
    _, idx = np.unique(imu.t, return_index=True)  # sorted, first occurrence of each stamp
    return imu.select(idx) if len(idx) else None


class OnlineEstimator:
    """Window fits of the stream for each clip's initialisation, and the odom trajectory of the chained clips.

    Usage per clip: ``init = est.initialise(clip, geometry)`` (or as ``anchor(..., init=lambda g:
    est.initialise(clip, g))``), then ``est.update(clip, anchor_result)`` -> ChainedClip or None. Deterministic:
    the same clips give the same output. ``state`` may be replaced between clips (tests inject a wrong prior)."""

    def __init__(self, *, options: OnlineOptions | None = None, init_options: InitOptions | None = None) -> None:
        self.options = options or OnlineOptions()
        self.init_options = init_options or InitOptions()
        self.state: OdomState | None = None
        self.trajectory = Trajectory()
        self.last = OnlineDecision()
        self._imu: ImuSamples | None = None
        self._window: list[WindowClip] = []
        self._bgs: list[tuple[float, np.ndarray]] = []  # (first stamp, own gyro-bias estimate) of recent clips
        self._rms_ref = 0.0  # median per-clip position residual of the last accepted window fit, m
        self._rejects = 0
        self._restarted = False
        self._last_end: float | None = None  # last frame of the previous clip seen, s
        self._pending: tuple[float, Placement] | None = None

    @property
    def g_O(self) -> np.ndarray:
        return np.array([0.0, 0.0, -self.init_options.gravity_norm])

    # ---- IMU bridge from the odom state ---------------------------------------------------------------------

    def _remember_imu(self, clip: Clip) -> None:
        imu = _merge_imu(_merge_imu(self._imu, clip.imu_history), clip.imu)
        if imu is not None:
            self._imu = imu.select(imu.t >= imu.t[-1] - self.options.imu_keep_s)

    def _imu_gap(self, t0: float, t1: float) -> str:
        """Why the kept IMU does not cover [t0, t1] ("" when it does)."""
        if self._imu is None:
            return "no IMU"
        return validate.check_imu(self._imu.window(t0, t1), np.array([t0, t1]), self.init_options) or ""

    def _bridge(self, t1: float) -> tuple[Placement, np.ndarray] | str:
        """The odom state propagated to t1 from its frame nearest before t1: (placement, v_O at t1), or why it
        cannot be."""
        st = self.state
        if st is None:
            return "no odom state"
        k = int(np.searchsorted(st.stamps, t1 + 1e-9, side="right")) - 1
        if k < 0:
            return f"clip starts at {t1:.3f} s, before the previous clip's first frame"
        R_k, p_k, v_k = st.T_OB[k, :3, :3], st.T_OB[k, :3, 3], st.v_O[k]
        gap = t1 - float(st.stamps[k])
        if gap < 1e-9:
            return Placement(R_k, p_k), v_k
        why = self._imu_gap(float(st.stamps[k]), t1)
        if why:
            return f"no IMU over the {gap:.2f} s bridge: {why}"
        stamps = np.array([st.stamps[k], t1])
        pre = preintegrate(self._imu.window(stamps[0], stamps[1]), stamps, st.bg)
        bridge = pre.propagate(R_k.T @ self.g_O, R_k.T @ v_k)  # in B_k, then rotated into odom
        return Placement(R_k @ bridge.R[1], p_k + R_k @ bridge.p[1]), R_k @ bridge.v[1]

    def _place(self, bridged: tuple[Placement, np.ndarray] | str) -> Placement:
        """The bridged placement, else the last pose (no IMU over the gap), else the odom origin."""
        if not isinstance(bridged, str):
            return bridged[0]
        if self.state is None:
            return Placement(np.eye(3), np.zeros(3))
        return Placement(self.state.T_OB[-1, :3, :3], self.state.T_OB[-1, :3, 3])

    def _filtered_bg(self, t1: float, bg: np.ndarray) -> np.ndarray:
        """Median [3] rad/s of the own gyro-bias estimates of the clips of the last ``bg_window_s`` seconds (the
        bias drifts slowly; the median ignores a clip whose visual rotations failed)."""
        self._bgs = [(t, b) for t, b in self._bgs if t >= t1 - self.options.bg_window_s] + [(t1, np.asarray(bg))]
        return np.median([b for _, b in self._bgs], axis=0)

    # ---- initialisation -------------------------------------------------------------------------------------

    def _restart(self, free: InitResult, why: str, seed: WindowClip | None = None, bg: np.ndarray | None = None,
                 T_BC: np.ndarray | None = None) -> InitResult:
        """Restart the window from ``seed`` when the clip's own initialisation is ok (a clip whose own scale is
        unobservable may have poses too poor to anchor the window), with its own position residual as the reference
        of the consistency test; the clip keeps its GT-free result."""
        self._window, self._rms_ref = [], 0.0
        if seed is not None and free.ok and not self._imu_gap(float(seed.stamps[0]), float(seed.stamps[-1])):
            self._window, self._rms_ref = [seed], float(self._system([seed], bg, T_BC).solve().rms[0])
        self._rejects, self._restarted = 0, True
        return self._decide(free, OnlineDecision(window=len(self._window), reset=why), free)

    def _decide(self, result: InitResult, decision: OnlineDecision, free: InitResult) -> InitResult:
        """Record the decision; the diagnostics keep the clip's own GT-free result beside it (``free_status``,
        ``free_scale``: what the paper's per-clip pipeline would have output)."""
        self.last = decision
        result.diagnostics.update(online=decision.describe(), free_status=free.status.value, free_scale=free.scale)
        return result

    def _system(self, clips: list[WindowClip], bg: np.ndarray, T_BC: np.ndarray) -> WindowSystem:
        imu = self._imu.window(float(clips[0].stamps[0]), float(clips[-1].stamps[-1]))
        return WindowSystem(clips, imu, bg, T_BC, gravity_norm=self.init_options.gravity_norm,
                            ba_weight=self.options.ba_weight, link_weight_s=self.options.velocity_link_s)

    def initialise(self, clip: Clip, geometry: Geometry) -> InitResult:
        """The clip's InitResult: from the window fit, or the GT-free one after a restart."""
        o = self.options
        self._remember_imu(clip)
        free = initialise_clip(clip, geometry, options=self.init_options)
        t1 = float(clip.stamps[0])
        gap = t1 - self._last_end if self._last_end is not None else 0.0
        self._last_end = float(clip.stamps[-1])
        bridged = self._bridge(t1)
        self._pending = (t1, self._place(bridged))
        if free.status is InitStatus.REJECTED:
            return self._restart(free, f"clip rejected ({free.reason})")
        bg = self._filtered_bg(t1, free.bg)
        member = WindowClip(np.asarray(clip.stamps, dtype=np.float64), np.asarray(geometry.T_wc, np.float64))
        window = [c for c in self._window if c.stamps[0] >= t1 - o.window_s]
        if not window:
            return self._restart(free, "no window yet" if not self._window else "window expired", member, bg,
                                 clip.T_BC)
        why = (f"gap of {gap:.2f} s > max_gap_s {o.max_gap_s} s" if gap > o.max_gap_s
               else f"clip out of order (starts at {t1:.3f} s)" if t1 <= float(window[-1].stamps[0])
               else self._imu_gap(float(window[0].stamps[0]), float(clip.stamps[-1])))
        if why:
            return self._restart(free, why, member, bg, clip.T_BC)

        # With the new clip, every clip must still fit about as well as the window's clips did: a clip whose poses
        # are wrong spreads its error over the whole window. (An outlier that got in anyway makes the next clips
        # fail too, and max_rejects of those restart the window.)
        clips = [*window, member]
        system = self._system(clips, bg, clip.T_BC)
        fit = system.solve()
        limit = max(o.residual_ratio * self._rms_ref, o.residual_floor_m)
        old = float(fit.rms[:-1].max())
        if not (fit.rms[-1] <= limit and old <= limit):
            self._rejects += 1
            if self._rejects >= o.max_rejects:
                return self._restart(free, f"{self._rejects} clips in a row inconsistent with the window",
                                     member, bg, clip.T_BC)
            reason = (f"position residual {1e3 * fit.rms[-1]:.1f} mm, the window's up to {1e3 * old:.1f} mm (limit "
                      f"{1e3 * limit:.1f} mm) in a window of {len(clips)} clips")
            return self._decide(InitResult(InitStatus.REJECTED, f"inconsistent with the online window: {reason}",
                                           bg=bg, diagnostics=dict(free.diagnostics)),
                                OnlineDecision(window=len(clips), rejected={"clip": reason}), free)
        self._rejects = 0
        rel = float(fit.scale_rel_sigma[-1])  # before the priors: they restate the previous window's data
        # Only a clip whose scale the window pins down joins it: a poorly determined scale is as often a sign of
        # wrong poses (which then bend g, v and ba for the clips after it) as of too little motion.
        if fit.scales[-1] > 0.0 and rel <= o.max_scale_rel_sigma:
            self._window, self._rms_ref = clips, float(np.median(fit.rms))

        # Priors from the odom state, each tested against the window's own estimate at the clip's first frame.
        k = len(clips) - 1
        g_win, v_win = system.state_at(k, fit)
        decision = OnlineDecision(window=len(clips))
        if not isinstance(bridged, str):
            place, v_O1 = bridged
            g_prior, v_prior = place.R_OB1.T @ self.g_O, place.R_OB1.T @ v_O1
            angle = math.degrees(float(so3.angle_between(g_prior, g_win)))
            dv = float(np.linalg.norm(v_prior - v_win))
            priors = []
            if angle > o.gravity_tol_deg:
                decision.rejected["g"] = f"{angle:.2f} deg from the window's gravity > {o.gravity_tol_deg} deg"
            elif o.gravity_weight_s2 > 0.0:
                priors.append(system.gravity_prior(k, g_prior, o.gravity_weight_s2))
                decision.used += ("g",)
            if dv > o.velocity_tol_mps:
                decision.rejected["v1"] = f"{dv:.2f} m/s from the window's velocity > {o.velocity_tol_mps} m/s"
            elif o.v1_weight_s > 0.0:
                priors.append(system.velocity_prior(k, v_prior, o.v1_weight_s))
                decision.used += ("v1",)
            if priors:
                fit = system.solve(tuple(priors))
                g_win, v_win = system.state_at(k, fit)
        s = float(fit.scales[-1])
        diag = dict(free.diagnostics, free_g=free.g, window_clips=len(clips), window_rms=fit.rms, ba=fit.ba,
                    scale_rel_sigma=rel)
        if not (s > 0.0 and rel <= o.max_scale_rel_sigma):
            return self._decide(InitResult(InitStatus.UNOBSERVABLE, f"scale unobservable over the online window "
                                           f"(s {s:.3g}, relative sigma {rel:.3g} > {o.max_scale_rel_sigma})",
                                           bg=bg, g=g_win, diagnostics=diag), decision, free)
        target = preintegrate(clip.imu, clip.stamps, bg, fit.ba).propagate(g_win, v_win, clip.T_BC)
        return self._decide(InitResult(InitStatus.OK, f"ok (online window of {len(clips)} clips)", bg=bg, g=g_win,
                                       scale=s, v1=v_win, gravity_source="online_window", target=target,
                                       diagnostics=diag), decision, free)

    # ---- chaining -------------------------------------------------------------------------------------------

    def update(self, clip: Clip, result: AnchorResult) -> ChainedClip | None:
        """Place the anchored clip in odom (levelled with its adopted gravity, yaw kept) and make it the state for
        the next clip's priors and bridge. A clip that is not ok, or that ``initialise`` did not see, is not
        placed (the window and the state carry on)."""
        init = result.init
        target = result.target or init.target
        pending, self._pending = self._pending, None
        if not init.ok or target is None or result.mode == "none" or pending is None \
                or pending[0] != float(clip.stamps[0]):
            return None
        place = pending[1]
        R_OB1 = gravity_align(place.R_OB1, init.g)
        T_BC = clip.T_BC
        T_B1B = T_BC @ result.geometry.T_wc @ so3.inv_T(T_BC)  # metric body poses in B1
        T_OB = so3.make_T(R_OB1, place.p_OB1) @ T_B1B
        v_O = target.v @ R_OB1.T
        if self._restarted and self.state is not None:
            self.trajectory.resets.append(float(clip.stamps[0]))
        self._restarted = False
        self.state = OdomState(np.asarray(clip.stamps, dtype=np.float64), T_OB, v_O, np.asarray(init.bg))
        chained = ChainedClip(self.state.stamps, T_OB, v_O)
        self.trajectory.extend(chained)
        return chained
