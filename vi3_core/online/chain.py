"""The continuous ``odom`` trajectory (REP-105: continuous, gravity-aligned, z up) that clips are chained into, and
``OdomChain``, which places each claimed clip in it, and each clip whose scale the online window knows well enough
for odometry (``OdomChain.places_unclaimed``) though not for a claim.

``T_OB`` are body (IMU frame) poses in odom; gravity in odom is [0, 0, -|g|] by construction. Every chained clip is
placed through the IMU from the last chained frame with both ends' velocities (the last pose without IMU;
``OdomChain.placement``), levelled with its gravity, yaw kept; a placement whose bridge has no IMU or a position
1-sigma above ``online_max_bridge_sigma`` starts a new segment of the trajectory (``Trajectory.resets``). The chain
composes every clip's poses on the last clip's without end: its rotations are made rotations again at each clip
(``so3.nearest_rotation``), so round-off never accumulates, however long the flight.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vi3_core import so3
from vi3_core.init import InitOptions, validate
from vi3_core.online.options import OnlineOptions
from vi3_core.preintegration import preintegrate
from vi3_core.types import AnchorResult, Clip, ImuSamples, InitResult, InitStatus

UP = np.array([0.0, 0.0, 1.0])


def gravity_align(R_ref: np.ndarray, g_B: np.ndarray) -> np.ndarray:
    """The attitude R_OB [3,3] nearest to ``R_ref`` that maps gravity ``g_B`` [3] (body frame) onto -z of odom:
    the smallest rotation of R_ref that levels it, so its yaw is kept."""
    u = R_ref @ (np.asarray(g_B, dtype=np.float64) / np.linalg.norm(g_B))
    axis = np.cross(u, -UP)
    angle = np.arctan2(np.linalg.norm(axis), float(u @ -UP))
    if np.linalg.norm(axis) < 1e-12:
        return R_ref.copy() if angle < 1.0 else so3.exp(np.pi * np.array([1.0, 0.0, 0.0])) @ R_ref
    return so3.exp(axis / np.linalg.norm(axis) * angle) @ R_ref


@dataclass(frozen=True)
class OdomState:
    """The last chained clip: stamps [n] s, T_OB [n,4,4] body poses in odom, v_O [n,3] m/s, bg [3] rad/s and ba [3]
    m/s^2 biases, v_sigma m/s and g_sigma rad: the largest 1-sigma of its first-frame velocity and gravity direction."""

    stamps: np.ndarray
    T_OB: np.ndarray
    v_O: np.ndarray
    bg: np.ndarray
    ba: np.ndarray
    v_sigma: float
    g_sigma: float


@dataclass(frozen=True)
class Placement:
    """Where the next clip's first body frame goes: R_OB1 [3,3], p_OB1 [3] m (re-levelled with the clip's gravity
    when it is chained), why it starts a new segment ("" when the bridge from the last chained clip holds), and the
    position 1-sigma (m, per axis) the IMU bridge to it adds (0 without one)."""

    R_OB1: np.ndarray
    p_OB1: np.ndarray
    new_segment: str = ""
    sigma: float = 0.0


@dataclass
class ChainedClip:
    """One clip placed in odom: stamps [n] s, T_OB [n,4,4] body poses, v_O [n,3] body velocities in odom, m/s."""

    stamps: np.ndarray
    T_OB: np.ndarray
    v_O: np.ndarray


class Trajectory:
    """The chained odom trajectory: every frame once, in time order (an overlapping clip adds only its new frames).

    stamps: [N] s; T_OB: [N,4,4] (views of buffers that grow by doubling, so that a flight of hours costs each clip
    the same); resets: first stamps of the clips that start a new segment, placed without a trustworthy IMU bridge
    from the previous chained clip (the first clip of the stream is not one), or the first after the stream was reset
    (``StreamEstimator.reset``: time went back, the trajectory then holds only the frames since, and its stamps may
    be earlier than the resets before). The position uncertainty of the newest frame relative to its segment's first
    frame: error_m, m, what the chained clips' relative errors add up to (each clip's metres flown, from the frame
    before its first new one, times its ``rel_sigma``, summed: the clips' scales and gravity are tied through the
    window, so their errors are correlated); bridge_var, m^2 per axis, what the IMU bridges between the segment's
    clips added (clips a busy worker dropped; independent, in quadrature); segment_start: the index of the current
    segment's first frame."""

    def __init__(self, *, resets: list[float] | None = None) -> None:
        self.resets: list[float] = list(resets or [])
        self.error_m = 0.0
        self.bridge_var = 0.0
        self.segment_start = 0
        self._n = 0
        self._stamps = np.zeros(0)
        self._T = np.zeros((0, 4, 4))

    @property
    def stamps(self) -> np.ndarray:
        return self._stamps[:self._n]

    @property
    def T_OB(self) -> np.ndarray:
        return self._T[:self._n]

    def start_segment(self, t: float) -> None:
        """The next frames start a new segment, its first frame at ``t`` s; its uncertainty starts from zero."""
        self.resets.append(t)
        self.error_m = self.bridge_var = 0.0
        self.segment_start = self._n

    def extend(self, clip: ChainedClip, *, rel_sigma: float = 0.0, bridge_sigma: float = 0.0) -> None:
        """Add the frames of ``clip`` after the newest one; ``rel_sigma``: the clip's relative position error (per
        metre flown), ``bridge_sigma``: m, the 1-sigma of the IMU bridge that placed it."""
        n = self._n
        new = clip.stamps > (self._stamps[n - 1] if n else -np.inf)
        P = np.concatenate([self._T[max(n - 1, self.segment_start):n, :3, 3], clip.T_OB[new, :3, 3]])
        self.error_m += rel_sigma * float(np.linalg.norm(np.diff(P, axis=0), axis=1).sum())
        self.bridge_var += bridge_sigma**2
        m = n + int(new.sum())
        if m > len(self._stamps):
            size = max(2 * len(self._stamps), m, 64)
            self._stamps = np.concatenate([self._stamps[:n], np.zeros(size - n)])
            self._T = np.concatenate([self._T[:n], np.zeros((size - n, 4, 4))])
        self._stamps[n:m], self._T[n:m] = clip.stamps[new], clip.T_OB[new]
        self._n = m


def imu_gap(imu: ImuSamples | None, t0: float, t1: float, options: InitOptions) -> str:
    """Why ``imu`` does not cover [t0, t1] s (its samples checked as a clip's are), "" when it does."""
    if imu is None:
        return "no IMU"
    return validate.check_imu(imu.window(t0, t1), np.array([t0, t1]), options) or ""


class OdomChain:
    """The claimed clips of a stream, and the unclaimed ones it ``places_unclaimed``, one after the other in odom:
    ``state`` (the last chained clip, where the next bridge and the IMU-rate propagation start; None before the first)
    and ``trajectory``.

    ``add(clip, result, imu)`` places an anchored clip (``imu``: the stream's kept IMU, covering the bridge from the
    last chained clip). Deterministic; not thread-safe."""

    def __init__(self, *, options: OnlineOptions, init_options: InitOptions) -> None:
        self.options, self.init_options = options, init_options
        self.state: OdomState | None = None
        self.trajectory = Trajectory()
        self._new_segment = False  # the next chained clip starts a new segment (after a forgotten chain)

    def continue_after(self, previous: Trajectory) -> None:
        """Go on from the trajectory of a chain that was forgotten (time went back, so its state no longer holds):
        its segments count on and the next chained clip starts a new one at the odom origin."""
        self.trajectory = Trajectory(resets=previous.resets)
        self._new_segment = bool(len(previous.stamps) or previous.resets)

    def places_unclaimed(self, init: InitResult) -> bool:
        """Whether a clip whose scale is not claimed goes into odom all the same: the online window fitted it with
        others (one clip alone is the clip's own initialisation), settled on a positive scale whose relative 1-sigma is
        at most ``odom_max_scale_sigma``. Its metres flown then count that sigma and its gravity's (it is levelled with
        the window's gravity, as a claimed clip is) in the odom's uncertainty (``Trajectory.error_m``), where the IMU
        bridge over it would add the bias's walk growing with T^2.5 (``placement``); its scale is still not published
        (no depth, points or poses). Its velocity's sigma widens only the bridge to it."""
        fit = init.fit
        return (init.status is InitStatus.UNOBSERVABLE and fit is not None and fit.window_clips > 1 and fit.settled
                and fit.lam > 0 and fit.scale_rel_sigma <= self.options.odom_max_scale_sigma
                and bool(np.all(np.isfinite(init.g))))

    def placement(self, t1: float, init: InitResult, v1: np.ndarray, imu: ImuSamples | None) -> Placement:
        """Where the clip starting at t1 goes: the odom state at its frame nearest before t1 carried to t1 through the
        IMU, with both ends' velocities (the state's, and the clip's own first-frame velocity ``v1`` [3], m/s in its
        first body frame); without IMU over the gap (or state), the last pose (or the origin), starting a new
        segment.

        Two ends: with v_a (state) and v_b (clip) in the body frame at t_k, v_b = v_a + g T + beta(T) gives
        p(T) = (v_a + v_b) T / 2 + alpha(T) - beta(T) T / 2: gravity drops out, and a constant accelerometer-bias
        error cancels (alpha and beta T / 2 grow alike), where a one-ended bridge v_a T + g T^2 / 2 + alpha(T) lets
        a gravity tilt or a bias error grow with T^2 (metres over ten seconds). What is left: the two velocities'
        errors times T / 2, the accelerometer noise (q_a T^1.5 / sqrt(12) with both ends held) and the bias's walk
        over the bridge, which does not cancel (q_b T^2.5 / sqrt(120): the error integral of b(s) (T / 2 - s) over a
        walk b of rate q_b; a consumer IMU's bridged 22 s about 3 m off at a 1-sigma of 0.2 m without it)."""
        st = self.state
        if st is None:
            return Placement(np.eye(3), np.zeros(3), "")
        k = int(np.searchsorted(st.stamps, t1 + 1e-9, side="right")) - 1
        if k < 0:
            return Placement(st.T_OB[-1, :3, :3], st.T_OB[-1, :3, 3],
                             f"clip starts at {t1:.3f} s, before the previous clip's first frame")
        R_k, p_k = st.T_OB[k, :3, :3], st.T_OB[k, :3, 3]
        T = t1 - float(st.stamps[k])
        if T < 1e-9:
            return Placement(R_k, p_k)
        max_bridge = self.options.online_max_bridge
        why = (f"gap of {T:.2f} s > online_max_bridge {max_bridge} s" if T > max_bridge
               else imu_gap(imu, float(st.stamps[k]), t1, self.init_options))
        if why:
            return Placement(st.T_OB[-1, :3, :3], st.T_OB[-1, :3, 3], f"no bridge over {T:.2f} s: {why}")
        stamps = np.array([st.stamps[k], t1])
        pre = preintegrate(imu.window(stamps[0], stamps[1]), stamps, init.bg, init.ba)
        v_a, v_b = R_k.T @ st.v_O[k], pre.R[1] @ v1
        d = 0.5 * (v_a + v_b) * T + pre.alpha[1] - 0.5 * pre.beta[1] * T
        v1_sigma = init.fit.v1_sigma if init.fit is not None else 0.0
        noise = self.init_options.noise_model
        sigma = math.hypot(0.5 * T * math.hypot(st.v_sigma, v1_sigma),
                           noise.accel_noise_density * T**1.5 / math.sqrt(12.0),
                           noise.accel_bias_walk * T**2.5 / math.sqrt(120.0))
        new = (f"bridge of {T:.2f} s has a position 1-sigma of {sigma:.2f} m > online_max_bridge_sigma "
               f"{self.options.online_max_bridge_sigma}") if sigma > self.options.online_max_bridge_sigma else ""
        return Placement(R_k @ pre.R[1], p_k + R_k @ d, new, sigma)

    def add(self, clip: Clip, result: AnchorResult, imu: ImuSamples | None) -> ChainedClip | None:
        """Place the anchored clip in odom (levelled with its gravity, yaw kept) and make it the state for the next
        clip's bridge (through ``imu``). A clip that is neither ok nor ``places_unclaimed`` is not placed (None); an
        unclaimed one is placed at the window's scale (its poses the backbone's times 1 / lam, as a claim's would be),
        its velocities the IMU's from the window's state."""
        init, fit, T_BC = result.init, result.init.fit, clip.T_BC
        target = result.target or init.target
        if init.ok and target is not None and result.mode != "none":
            T_wc, v1 = result.geometry.T_wc, init.v1
        elif self.places_unclaimed(init):
            T_wc = result.base.T_wc.copy()
            T_wc[:, :3, 3] /= fit.lam
            v1 = fit.v1
            target = preintegrate(clip.imu, clip.stamps, init.bg, init.ba).propagate(init.g, v1, T_BC)
        else:
            return None
        place = self.placement(float(clip.stamps[0]), init, v1, imu)
        R_OB1 = gravity_align(place.R_OB1, init.g)
        T_B1B = T_BC @ T_wc @ so3.inv_T(T_BC)  # metric body poses in B1
        T_OB = so3.make_T(R_OB1, place.p_OB1) @ T_B1B
        T_OB[:, :3, :3] = so3.nearest_rotation(T_OB[:, :3, :3])  # the next clip composes on it: no round-off kept
        v_O = target.v @ R_OB1.T
        new_segment = (place.new_segment and self.state is not None) or self._new_segment
        if new_segment:  # at the clip's first new frame
            last = self.trajectory.stamps[-1] if len(self.trajectory.stamps) else -np.inf
            self.trajectory.start_segment(float(clip.stamps[np.argmax(clip.stamps > last)]))
            self._new_segment = False
        self.state = OdomState(np.asarray(clip.stamps, dtype=np.float64), T_OB, v_O, np.asarray(init.bg),
                               np.asarray(init.ba), fit.v1_sigma if fit is not None else 0.0,
                               fit.g_sigma if fit is not None else 0.0)

        chained = ChainedClip(self.state.stamps, T_OB, v_O)
        # the clip's relative position error: its scale's and its levelling's (a tilt turns metres flown sideways)
        rel = math.hypot(fit.scale_rel_sigma, fit.g_sigma) if fit is not None else init.scale_sigma / init.scale
        self.trajectory.extend(chained, rel_sigma=rel, bridge_sigma=0.0 if new_segment else place.sigma)
        return chained


__all__ = ["ChainedClip", "OdomChain", "OdomState", "Placement", "Trajectory", "gravity_align", "imu_gap"]
