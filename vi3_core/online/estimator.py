"""``OnlineEstimator``: metric state carried across the clips of a stream (beyond the paper, which treats every clip
on its own), and the chaining of the clips into one continuous odom trajectory (``chain.OdomChain``).

Per clip: (1) the clip's own GT-free initialisation runs as always (its data checks, its gyro bias, and its visual
noise from its own fit); (2) its rotations are checked against the gyro with the stream's bias (a backbone failure
is rejected before any scale); (3) the clip is fitted with the window (``window.Window``: the clips of the last
``online_window`` seconds and the marginal prior of the ones before) and rejected, window unchanged, when it is
inconsistent with the window at ``online_consistency_p``: its residual (a chi-square test), or its own scale
against the window's (``scale_agreement``: one clip whose own fit is off cannot carry the window); (4) its scale,
gravity, velocity and biases come from that fit, and the scale is claimed only when its relative 1-sigma passes
``max_scale_sigma``. Clips join the window whatever their own sigma: evidence accumulates, so gentle motion earns its
scale over time. A gap in the IMU (or a bridge longer than ``online_max_bridge``), an out-of-order clip, or
``online_max_rejects`` inconsistent clips in a row restart the window (the accelerometer bias survives as a prior,
the gyro-bias median and the odom attitude survive as they are); a window of one clip (the first, or a restart) is
claimed only where the clip's own initialisation is. Every claimed clip is then placed in odom (``update``), and so is
a clip whose window scale is known well enough for odometry though not for a claim (``OdomChain.places_unclaimed``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import stats

from vi3_core.init import InitOptions, initialise_clip
from vi3_core.init.gyro_bias import body_rotations, rotation_check
from vi3_core.init.initializer import rotation_failure
from vi3_core.online.chain import ChainedClip, OdomChain, OdomState, Trajectory, imu_gap
from vi3_core.online.link import MeasuredLink, SharedFrames, measure_link
from vi3_core.online.options import OnlineOptions
from vi3_core.online.window import Member, Solution, Window, members_span
from vi3_core.preintegration import preintegrate
from vi3_core.threads import single_blas_thread
from vi3_core.types import AnchorResult, Clip, Geometry, ImuSamples, InitResult, InitStatus, ScaleFit

MAX_START_REL_SIGMA = 1.0  # a clip's own scale no better than this (relative 1-sigma) is no start (``starts_from_own``)


@dataclass
class OnlineDecision:
    """What the estimator did with a clip: window size (clips fitted jointly, 0: none) and span (s), whether a marginal
    prior from earlier clips was used, rejected {name: reason} ("clip": the clip itself), reset reason ("" if none),
    ``own``: the clip's own GT-free initialisation (what the paper's per-clip pipeline with the error model would
    output; None before the clip was seen), whether the clip ``joined`` the window, the scale ``link`` to the clip
    before it that the window fit used (None: none) and ``link_note``, what became of a link otherwise; ``scale_p``:
    the p-value of the clip's own scale against the window's (``scale_agreement``; NaN where it was not tested);
    ``levels``: the noise levels (IMU, visual) learnt so far (``Window.levels``; empty where not estimated);
    ``traj_depth_sigma``: the backbone's 1-sigma of the clip's trajectory scale against its depth's (``Geometry``;
    0: it does not say), which bounds what the window's links can tell of the clip's trajectory."""

    window: int = 0
    span_s: float = 0.0
    prior: bool = False
    rejected: dict[str, str] = field(default_factory=dict)
    reset: str = ""
    own: InitResult | None = None
    joined: bool = False
    link: MeasuredLink | None = None
    link_note: str = ""
    scale_p: float = float("nan")
    levels: tuple[float, ...] = ()
    traj_depth_sigma: float = 0.0

    @property
    def earned(self) -> str:
        """How the clip's scale was earned: "linked" (through the frames it shares with the clip before it, and that
        clip's window), "window" (the window's IMU ties alone) or "own" (the clip alone: a new window)."""
        return "linked" if self.link is not None else "window" if self.window > 1 else "own"

    def describe(self) -> str:
        parts = [f"window {self.window} clips over {self.span_s:.1f} s; prior: {'yes' if self.prior else 'none'}"]
        if self.joined:
            parts.append(f"scale: {self.earned}" + (f" ({self.link.describe()})" if self.link is not None else ""))
        if self.link_note:
            parts.append(f"link: {self.link_note}")
        if math.isfinite(self.scale_p):
            parts.append(f"own scale agrees: p = {self.scale_p:.2g}")
        if self.traj_depth_sigma > 0:
            parts.append(_traj_depth_text(self.traj_depth_sigma))
        if self.levels:
            parts.append("noise levels: IMU {:.2g}, visual {:.2g}".format(*self.levels))
        parts += [f"{name} rejected: {why}" for name, why in sorted(self.rejected.items())]
        if self.reset:
            parts.append(f"reset: {self.reset}")
        return "; ".join(parts)


def _traj_depth_text(sigma: float) -> str:
    """How a decision and an unobservable clip's reason name the clip's ``traj_depth_sigma`` (relative)."""
    return f"the clip's trajectory against its depth +- {100 * sigma:.2g} %"


def scale_agreement(own: ScaleFit, lam: float, rel_sigma: float) -> tuple[float, float]:
    """Whether a clip's own scale (``own``: its fit alone) agrees with the window's (``lam`` = 1 / scale, relative
    1-sigma ``rel_sigma``): z and the two-sided p-value of lam_own - lam_window, whose variance is the own estimate's
    minus the window's (the window holds the clip's own evidence and more: a Hausman test). p = 1 where the window
    knows the clip's scale no better than the clip alone."""
    var = (own.scale_rel_sigma * own.lam) ** 2 - (rel_sigma * lam) ** 2
    if not (own.lam > 0 and lam > 0 and np.isfinite(var) and var > 0):
        return 0.0, 1.0
    z = (own.lam - lam) / math.sqrt(var)
    return z, float(math.erfc(abs(z) / math.sqrt(2.0)))


def starts_from_own(own: ScaleFit) -> bool:
    """Whether the window starts a clip's scale and velocity from the clip's own fit ``own``: where that scale is
    positive and known to better than 100 % (``MAX_START_REL_SIGMA``); else from its neighbours through their scale
    links (``window.starting_scales``). A clip of a generated flight whose own scale came out at 1/86 of its
    neighbours' at a relative sigma of 4630 started the window's Gauss-Newton there, and the whole window ran off."""
    return bool(own.lam > 0 and own.scale_rel_sigma < MAX_START_REL_SIGMA)


def moves(geometry: Geometry) -> bool:
    """Whether the backbone's cameras move at all (a clip it could not reconstruct has translations of exactly 0)."""
    t = geometry.T_wc[:, :3, 3]
    return bool(np.isfinite(t).all() and np.abs(t).max(initial=0.0) > 0.0)


SAME_SAMPLE_S = 1e-6  # s: IMU stamps closer than this are one sample


def _merge_imu(a: ImuSamples | None, b: ImuSamples | None) -> ImuSamples | None:
    """Both sample sets, sorted, each sample once (the first of stamps within ``SAME_SAMPLE_S``), non-finite samples
    dropped (a gap they leave is caught later)."""
    parts = [p for p in (a, b) if p is not None and len(p)]
    if not parts:
        return None
    imu = ImuSamples.concatenate([replace(p, orientation=None) for p in parts])
    finite = np.isfinite(imu.t) & np.isfinite(imu.gyro).all(1) & np.isfinite(imu.accel).all(1)
    imu = imu.select(np.flatnonzero(finite))
    order = np.argsort(imu.t, kind="stable")
    t = imu.t[order]
    # each sample once: two stamps within a microsecond are one sample (moved between clocks and back by round-off)
    keep = order[np.concatenate([[True], np.diff(t) > SAME_SAMPLE_S])] if len(order) else order
    return imu.select(keep) if len(keep) else None


def _median_bias(bgs: list[tuple[float, np.ndarray]]) -> tuple[np.ndarray, float]:
    """Median [3] rad/s of (stamp, own gyro-bias estimate) pairs and its 1-sigma (rad/s, largest axis, from their
    spread; 0 with fewer than three)."""
    b = np.array([bg for _, bg in bgs])
    med = np.median(b, axis=0)
    spread = 1.4826 * np.median(np.abs(b - med), axis=0).max() / math.sqrt(len(b)) if len(b) > 2 else 0.0
    return med, float(spread)


class OnlineEstimator:
    """Window fits of the stream for each clip's initialisation, and the odom trajectory of the chained clips.

    Usage per clip: ``init = est.initialise(clip, geometry)`` (or as ``anchor(..., init=lambda g:
    est.initialise(clip, g))``), then ``est.update(clip, anchor_result)`` -> ChainedClip or None. Deterministic:
    the same clips give the same output. Needs the "eiv" scale solver (its error model)."""

    def __init__(self, *, options: OnlineOptions | None = None, init_options: InitOptions | None = None) -> None:
        self.options = options or OnlineOptions()
        self.init_options = init_options or InitOptions()
        if self.init_options.scale_solver != "eiv":
            raise ValueError("the online window needs scale_solver 'eiv' (its error model); the paper's solvers run "
                             "on independent clips only")
        self.window = Window(noise=self.init_options.noise_model, gravity_norm=self.init_options.gravity_norm,
                             window_s=self.options.online_window, max_clips=self.options.online_max_clips,
                             visual_drift=self.init_options.visual_drift,
                             noise_levels=self.init_options.noise_levels)
        self.chain = OdomChain(options=self.options, init_options=self.init_options)
        self.last = OnlineDecision()
        self._imu: ImuSamples | None = None
        self._imu_shift = 0.0  # s, the clock the kept IMU is on (``Clip.imu_shift``)
        self._bgs: list[tuple[float, np.ndarray]] = []  # (first stamp, own gyro-bias estimate) of recent clips
        self._rejects = 0
        self._window_claimed = False  # the window (since its last restart) has claimed a scale
        self._last_start: float | None = None  # first frame of the previous clip seen, s
        self._pending: float | None = None  # first stamp of the clip ``initialise`` saw last
        self.shared: SharedFrames | None = None  # the last frames of the newest clip in the window
        self._reset = ""  # why an estimator before this one was forgotten (``continue_after``), until a clip joins

    @property
    def state(self) -> OdomState | None:
        """The last chained clip (``OdomChain.state``)."""
        return self.chain.state

    @property
    def trajectory(self) -> Trajectory:
        """The chained odom trajectory (``OdomChain.trajectory``)."""
        return self.chain.trajectory

    def continue_after(self, previous: Trajectory, reason: str) -> None:
        """Go on from the trajectory of an estimator that was forgotten (``reason``: time went back, so nothing it
        knew holds): its segments count on, the next chained clip starts a new one at the odom origin, and the first
        clip that joins the window names ``reason`` as its reset."""
        self.chain.continue_after(previous)
        self._reset = reason

    # ---- the IMU kept for the window and the bridges ---------------------------------------------------------

    def _remember_imu(self, clip: Clip) -> None:
        """Keep the IMU of ``clip`` for the window's ties and the bridges to the next clips, all of it on the clip's
        clock: the kept samples move by the change of ``Clip.imu_shift`` (the rig's applied time offset), so that a
        sample never enters twice at two times."""
        old = self._imu
        if old is not None and clip.imu_shift != self._imu_shift:
            old = old.shifted(clip.imu_shift - self._imu_shift)
        imu = _merge_imu(_merge_imu(old, clip.imu_history), clip.imu)
        if imu is not None:
            self._imu, self._imu_shift = imu.select(imu.t >= imu.t[-1] - self.options.imu_keep_s), clip.imu_shift

    def _filtered_bg(self, t1: float, bg: np.ndarray) -> tuple[np.ndarray, float]:
        """Median [3] rad/s of the own (rotation-based) gyro-bias estimates of the clips of the last
        ``online_bg_window`` seconds, and its 1-sigma (rad/s, largest axis, from their spread; the median ignores a clip
        whose rotations failed)."""
        self._bgs = [(t, b) for t, b in self._bgs if t >= t1 - self.options.online_bg_window] + [(t1, np.asarray(bg))]
        return _median_bias(self._bgs)

    @property
    def gyro_bias(self) -> tuple[np.ndarray, float] | None:
        """The filtered gyro bias after the last clip (``_filtered_bg``) and its 1-sigma (rad/s), floored at the noise
        model's ``gyro_bias_sigma``: for the next clip's backbone (``GyroRotations``); None before three clips gave
        their own estimate (no spread to say how good the median is)."""
        if len(self._bgs) < 3:
            return None
        med, spread = _median_bias(self._bgs)
        return med, max(spread, self.init_options.gyro_bias_sigma)

    # ---- initialisation -------------------------------------------------------------------------------------

    def _decide(self, result: InitResult, decision: OnlineDecision, own: InitResult) -> InitResult:
        """Record the decision (``last``) with the clip's own result beside it."""
        self.last = replace(decision, own=own)
        return result

    def _link(self, clip: Clip, geometry: Geometry, sigma_v: float) -> tuple[MeasuredLink | None, str]:
        """The link of ``clip`` (predicted as ``geometry``, its own visual noise ``sigma_v``) to the clip whose last
        frames are ``shared``, when it starts with them; else None and why (empty without ``shared_frames``)."""
        k, shared = self.options.shared_frames, self.shared
        if not k:
            return None, ""
        if shared is None:
            return None, "none (no earlier clip in the window)"
        if not shared.starts(clip):
            return None, (f"none (the clip does not start with the {k} frame(s) kept from the clip at "
                          f"{shared.clip_start:.3f} s)")
        measured = measure_link(shared, geometry, sigma_v, sigma_floor=self.options.link_sigma_floor)
        if isinstance(measured, str):
            return None, f"none ({measured})"
        return (measured.across(shared.bridge, shared.clip_start) if shared.bridge is not None else measured), ""

    def _refused_link(self, sol: Solution) -> str:
        """Why the newest member's scale link is inconsistent with the window fit ``sol`` ("" when it is not, or is
        not used): its standardised residual, a chi-square of one degree of freedom, below ``online_consistency_p``.
        A link that alone fixes its clip's scale (leverage near one) cannot be tested and is taken."""
        k = len(sol.members) - 1
        if not sol.linked(k):
            return ""
        chi2, dof = float(sol.result.scale_chi2[k - 1]), float(sol.result.scale_dof[k - 1])
        if dof < 0.05:
            return ""
        p = float(stats.chi2.sf(chi2 / dof, 1))
        if p >= self.options.online_consistency_p:
            return ""
        return (f"the window puts the scale ratio {math.sqrt(chi2 / dof):.1f} sigma from the measured one (p = {p:.1e}"
                f" < online_consistency_p {self.options.online_consistency_p:g})")

    def _restart_reason(self, t1: float, t_end: float) -> str:
        """Why the window cannot go on with a clip spanning [t1, t_end] ("" when it can)."""
        if not len(self.window):
            return ""
        first, last = float(self.window.members[0].stamps[0]), float(self.window.members[-1].stamps[0])
        if t1 <= last:
            return f"clip out of order (starts at {t1:.3f} s, the previous clip at {last:.3f} s)"
        gap = t1 - float(self.window.members[-1].stamps[-1])
        if gap > self.options.online_max_bridge:
            return f"gap of {gap:.2f} s > online_max_bridge {self.options.online_max_bridge} s"
        why = imu_gap(self._imu, first, t_end, self.init_options)
        return f"IMU does not cover the window: {why}" if why else ""

    def initialise(self, clip: Clip, geometry: Geometry) -> InitResult:
        """The clip's InitResult from the window fit (see the module docstring)."""
        with single_blas_thread():
            return self._initialise(clip, geometry)

    def _initialise(self, clip: Clip, geometry: Geometry) -> InitResult:
        o, io = self.options, self.init_options
        self._remember_imu(clip)
        free = initialise_clip(clip, geometry, options=io)
        t1, t_end = float(clip.stamps[0]), float(clip.stamps[-1])
        self._pending = t1
        decision = OnlineDecision(window=len(self.window), span_s=self.window.span_s,
                                  prior=self.window.prior is not None, traj_depth_sigma=geometry.traj_depth_sigma)
        if free.status is InitStatus.REJECTED:  # bad data or a backbone failure: the window goes on without it
            return self._decide(free, replace(decision, rejected={"clip": free.reason}), free)
        bg, bg_sigma = self._filtered_bg(t1, free.bg)
        worst, i, j = rotation_check(clip.imu, clip.stamps, body_rotations(geometry.T_wc[:, :3, :3], clip.T_BC),
                                     bg).worst()
        if worst > io.max_rotation_error:
            why = rotation_failure(worst, i, j, io.max_rotation_error) + " (the stream's gyro bias)"
            return self._decide(InitResult(InitStatus.REJECTED, why, bg=bg, diagnostics=dict(free.diagnostics)),
                                replace(decision, rejected={"clip": why}), free)
        own = free.fit
        if own is None or not np.isfinite(own.sigma_v) or not moves(geometry):
            # Poses without translation say nothing of a scale (the backbone saw no parallax, or no motion): the clip
            # stays out, the window goes on. Every other clip's evidence joins, however weak, zero or negative its
            # own scale: only the claim is gated, and a window of clips that each say little says much.
            why = f"its poses carry no scale ({free.reason})"
            return self._decide(InitResult(InitStatus.UNOBSERVABLE, f"scale unobservable: {why}", bg=bg,
                                           fit=own, diagnostics=dict(free.diagnostics)),
                                replace(decision, rejected={"clip": why}), free)
        measured, link_note = self._link(clip, geometry, own.sigma_v)
        sure = starts_from_own(own)
        member = Member(np.asarray(clip.stamps, np.float64), np.asarray(geometry.T_wc, np.float64),
                        sigma_v=own.sigma_v, lam=own.lam if sure else float("nan"),
                        v=np.asarray(own.v1) if sure else np.full(3, np.nan), g=np.asarray(free.g), link=measured,
                        traj_depth_sigma=geometry.traj_depth_sigma)
        reset, self._reset = self._restart_reason(t1, t_end) or self._reset, ""
        if reset:
            gap = t1 - (self._last_start if self._last_start is not None else t1)
            self.window.restart(ba_widen=io.accel_bias_walk**2 * max(gap, 0.0))
            self._rejects, self._window_claimed = 0, False
        self._last_start = t1
        sol = self.window.solve(member, self._imu, bg, bg_sigma, clip.T_BC)
        k = len(sol.members) - 1
        refused = self._refused_link(sol)
        if refused:
            measured, member.link, link_note = None, None, f"rejected: {refused}"
            sol = self.window.solve(member, self._imu, bg, bg_sigma, clip.T_BC)
        res = sol.result
        chi2 = float(res.chi2[k] + (res.link_chi2[k - 1] if k else 0.0))
        dof = float(res.dof[k] + (res.link_dof[k - 1] if k else 0.0))
        p = float(stats.chi2.sf(chi2, dof)) if (k or sol.priors) else 1.0
        z, p_scale = scale_agreement(own, float(res.state.lam[k]), float(res.scale_rel_sigma[k]))
        if min(p, p_scale) < o.online_consistency_p:
            self._rejects += 1
            why = (f"normalised residual {chi2 / dof:.2f} over {dof:.1f} degrees of freedom (p = {p:.1e} < "
                   f"{o.online_consistency_p:g}) in a window of {k + 1} clips") if p < o.online_consistency_p else \
                (f"its own scale is {abs(z):.1f} sigma from the window's (p = {p_scale:.1e} < "
                 f"{o.online_consistency_p:g}) in a window of {k + 1} clips")
            # A window that has not claimed a scale yet has nothing to defend: the clip that disagrees with it
            # starts a new one (after a hover or a stretch of bad data the new clip is as likely to be right).
            if self._rejects < o.online_max_rejects and self._window_claimed:
                if o.shared_frames and measured is not None and measured.via is None:
                    # its depth still ties the next clip to the window: the next links across it
                    self.shared = SharedFrames.of(clip, geometry, k=o.shared_frames, sigma_v=own.sigma_v,
                                                  bridge=measured)
                return self._decide(InitResult(InitStatus.REJECTED, f"inconsistent with the online window: {why}",
                                               bg=bg, fit=own, diagnostics=dict(free.diagnostics)),
                                    replace(decision, rejected={"clip": why}, scale_p=p_scale), free)
            reset = (f"{self._rejects} clips in a row inconsistent with the window" if self._window_claimed
                     else f"inconsistent with a window that claimed no scale yet ({why})")
            self.window.restart()
            self._window_claimed = False
            sol = self.window.solve(member, self._imu, bg, bg_sigma, clip.T_BC)
            k, res = 0, sol.result
            z, p_scale = scale_agreement(own, float(res.state.lam[k]), float(res.scale_rel_sigma[k]))
        self._rejects = 0
        self.window.commit(sol)
        if self.options.shared_frames:
            self.shared = SharedFrames.of(clip, geometry, k=self.options.shared_frames, sigma_v=own.sigma_v)
        if measured is not None and not sol.linked(k):  # the clip it links to left the window (a restart)
            measured, link_note = None, "not used: the window restarted"
        span = members_span(sol.members)
        decision = OnlineDecision(window=k + 1, span_s=span, prior=bool(sol.priors), reset=reset, joined=True,
                                  link=measured, link_note=link_note, scale_p=p_scale,
                                  levels=tuple(self.window.levels) if self.window.noise_levels else (),
                                  traj_depth_sigma=geometry.traj_depth_sigma)
        g_k, v_k = sol.frame_state(k)
        s, rel = float(res.scale[k]), float(res.scale_rel_sigma[k])
        g_sigma, v_sigma = res.state_sigma(k)
        fit = ScaleFit(lam=float(res.state.lam[k]), scale_rel_sigma=rel, v1=v_k, v1_sigma=v_sigma, g_sigma=g_sigma,
                       sigma_v=own.sigma_v, dof=float(res.dof[k]), variance_factor=res.variance_factor,
                       settled=res.settled(k), window_clips=k + 1, time_offset=res.state.td,
                       time_offset_sigma=res.time_offset_sigma)
        diag = dict(free.diagnostics)
        st = res.state
        # A window of one clip (the stream's first, or a restart) has nothing the clip's own initialisation lacks
        # but the accelerometer-bias prior, and none of its checks: a clip flown at constant velocity fitted alone
        # went off to lam -> 0, v -> 1e6 m/s, where the linearisation gave that absurd scale a 3 % sigma (before
        # ``MetricFit._decomposed`` scaled its columns, which also let a clip's own initialisation claim one).
        passes = s > 0.0 and rel <= io.max_scale_sigma
        if not passes or not fit.settled or not (k or free.ok):
            tds = geometry.traj_depth_sigma
            if not passes:
                why = (f"scale unobservable over the online window (relative sigma {rel:.3g} > max_scale_sigma "
                       f"{io.max_scale_sigma}; {k + 1} clips over {span:.1f} s"
                       + (f"; {_traj_depth_text(tds)}" if tds > 0 else "") + ")")
            elif not fit.settled:
                why = (f"the online window's fit has not settled: the Gauss-Newton step still to go moves the clip's "
                       f"scale by {res.step_sigmas(k):.2g} sigma ({k + 1} clips over {span:.1f} s)")
            else:
                why = f"a window of one clip claims only what the clip's own initialisation does ({free.reason})"
            return self._decide(InitResult(InitStatus.UNOBSERVABLE, why, bg=st.bg, g=g_k, ba=st.ba, fit=fit,
                                           diagnostics=diag), decision, free)
        target = preintegrate(clip.imu, clip.stamps, st.bg, st.ba).propagate(g_k, v_k, clip.T_BC)
        self._window_claimed = True
        return self._decide(InitResult(InitStatus.OK, f"ok (online window of {k + 1} clips)", bg=st.bg, g=g_k,
                                       scale=s, scale_sigma=rel * s, ba=st.ba, v1=v_k, gravity_source="online_window",
                                       target=target, fit=fit, diagnostics=diag), decision, free)

    def update(self, clip: Clip, result: AnchorResult) -> ChainedClip | None:
        """Place the anchored clip in odom (``OdomChain.add``) through the kept IMU. A clip that is neither ok nor
        ``OdomChain.places_unclaimed``, or that ``initialise`` did not see last, is not placed."""
        pending, self._pending = self._pending, None
        if pending != float(clip.stamps[0]):
            return None
        return self.chain.add(clip, result, self._imu)


__all__ = ["OnlineDecision", "OnlineEstimator"]
