"""The online window: the clips of the last seconds fitted jointly, and what older clips said kept as a prior (beyond
the paper, which fits every clip on its own).

Over one 0.75 s clip a constant acceleration is nearly indistinguishable from a gravity tilt, and at a 3DFM's noise a
single clip's scale is rarely determined to a few per cent. Clips linked by continuous IMU share gravity and the
biases, and their velocities are tied through the IMU, so a clip flown at nearly constant velocity still gets its
scale from a velocity that earlier, better excited clips fixed. ``vi3_core.fit.MetricFit`` solves the window (one
scale and first-frame velocity per clip, each clip's visual noise from its own fit); clips that fall out of it are
marginalised (``vi3_core.fit.marginalise``) into a Gaussian prior on gravity, the biases and the velocity at the first
clip that stays, so evidence accumulates instead of expiring with the window.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from vi3_core.fit import (
    FitClip,
    FitResult,
    GaussianPrior,
    ImuNoiseModel,
    MetricFit,
    PriorLayout,
    ScaleLink,
    fit_stamps,
    marginalise,
)
from vi3_core.online.link import MeasuredLink
from vi3_core.preintegration import preintegrate
from vi3_core.types import ImuSamples

BA_FLOOR = 0.01  # m/s^2: no window's accelerometer-bias estimate is carried across a restart as better than this
LEVEL_PRIOR = 1.0  # the noise levels' prior: log-normal about the noise model's (1), this 1-sigma in the logarithm
LEVEL_STEP = 1.0  # the most a level's logarithm moves per clip


@dataclass
class Member:
    """A clip in the window: stamps [n] s; T_wc [n,4,4] backbone camera poses in its first camera frame (model units);
    sigma_v: its visual noise (model units, per axis, from its own fit); its latest estimates in its own first body
    frame: lam (1 / scale; NaN: none yet), v [3] m/s, g [3] m/s^2; and its scale link (None: unlinked) to the clip
    that started at ``link.clip_start`` s, which the fit uses when that clip is the member before it;
    traj_depth_sigma: its ``Geometry``'s (``FitClip``)."""

    stamps: np.ndarray
    T_wc: np.ndarray
    sigma_v: float
    lam: float
    v: np.ndarray
    g: np.ndarray
    link: MeasuredLink | None = None
    traj_depth_sigma: float = 0.0


def starting_scales(lam: np.ndarray, links: Sequence[ScaleLink | None]) -> np.ndarray:
    """Where the window's fit starts the members' scales: lam [K] (1 / scale) where it is sure (positive: the clip's
    own, or the window's last estimate of it), else the neighbour's through their scale link (links [K-1], link k-1
    between members k-1 and k; None: a ratio of 1): two clips of one scene, normalised alike, are at like scales. A
    member takes the one before it, the first ones the first sure one after them (from its own least-squares scale
    a window's first clip started negative, and Gauss-Newton ran off to inverse scales of 1e6 of both signs). NaN where
    no member is sure: ``MetricFit.initial_state`` then solves for them."""
    start = np.where(np.isfinite(lam) & (lam > 0), lam, np.nan)
    ratio = np.array([math.exp(link.log_ratio) if link is not None else 1.0 for link in links])  # lam_k / lam_k-1
    for k in range(1, len(start)):
        if np.isnan(start[k]):
            start[k] = start[k - 1] * ratio[k - 1]
    for k in range(len(start) - 2, -1, -1):
        if np.isnan(start[k]):
            start[k] = start[k + 1] / ratio[k]
    return start


def members_span(members: list[Member]) -> float:
    """s from the first member's first frame to the last member's last frame (0 for none)."""
    return float(members[-1].stamps[-1] - members[0].stamps[0]) if members else 0.0


@dataclass
class Solution:
    """A window fit: ``members`` fitted (the new clip last), its ``MetricFit`` and ``FitResult``, the priors used."""

    members: list[Member]
    fit: MetricFit
    result: FitResult
    priors: tuple[GaussianPrior, ...]

    def linked(self, k: int) -> bool:
        """Whether member k's scale link to member k-1 is in the fit."""
        return any(j == k for j, _, _ in self.fit.scale_links)

    def frame_state(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(g [3], v [3]) at member k's first frame, in that body frame."""
        R_f = self.fit.pre.R[self.fit.blocks[k].first]
        s = self.result.state
        return R_f.T @ s.g, R_f.T @ s.v[k]


class Window:
    """The members of the current window, the marginal prior of the clips before them, the biases' last estimates
    (for a restart) and, with ``noise_levels``, the sensors' noise levels learnt over the flight (``_learn_levels``).
    ``solve`` fits a candidate clip with them without changing anything; ``commit`` makes that fit the window and
    marginalises members older than ``window_s`` (or beyond ``max_clips``)."""

    def __init__(self, *, noise: ImuNoiseModel, gravity_norm: float, window_s: float, max_clips: int,
                 visual_drift: bool = True, noise_levels: bool = False) -> None:
        self.noise, self.G, self.window_s, self.max_clips = noise, gravity_norm, window_s, max_clips
        self.visual_drift, self.noise_levels = visual_drift, noise_levels
        # the noise levels (imu_level, visual_level: ``MetricFit``) and the information [2,2] in their logarithms
        # gathered so far: properties of the sensors, carried across restarts
        self.levels = np.ones(2)
        self.level_info = np.eye(2) / LEVEL_PRIOR**2
        self.members: list[Member] = []
        self.prior: GaussianPrior | None = None
        self.ba: tuple[np.ndarray, np.ndarray] | None = None  # last (ba [3], covariance [3,3]) estimate

    def __len__(self) -> int:
        return len(self.members)

    @property
    def span_s(self) -> float:
        """s the members span (``members_span``)."""
        return members_span(self.members)

    def restart(self, *, ba_widen: float = 0.0) -> None:
        """Drop the members and the marginal prior; the accelerometer bias's last estimate survives as a prior, its
        covariance widened by ``ba_widen`` (m/s^2)^2 per axis (its random walk over the gap)."""
        self.members, self.prior = [], None
        if self.ba is not None and np.all(np.isfinite(self.ba[0])) and np.all(np.isfinite(self.ba[1])):
            mean, cov = self.ba
            w, V = np.linalg.eigh(0.5 * (cov + cov.T))
            cov = (V * np.maximum(w, BA_FLOOR**2)) @ V.T + ba_widen * np.eye(3)
            sqrt_info = np.zeros((3, PriorLayout.n))
            sqrt_info[:, PriorLayout.ba] = np.linalg.cholesky(np.linalg.inv(cov)).T
            center = PriorLayout.vector(np.zeros(3), mean, np.zeros(3), np.zeros(3), 0.0, 0.0)
            self.prior = GaussianPrior(center, sqrt_info, np.zeros(3))

    def solve(self, new: Member, imu: ImuSamples, bg: np.ndarray, bg_sigma: float, T_BC: np.ndarray) -> Solution:
        """Fit the members and ``new`` (last) with the prior; ``imu`` must cover them all. The starting point is each
        member's latest estimate (the new clip's own fit for it), gravity from the first member."""
        members = [*self.members, new]
        clips = [FitClip(m.stamps, m.T_wc, m.sigma_v, m.traj_depth_sigma) for m in members]
        stamps = fit_stamps(clips)
        pre = preintegrate(imu.window(float(stamps[0]), float(stamps[-1])), stamps, bg, jacobians=True)
        links = [m.link.link if m.link is not None and m.link.clip_start == float(prev.stamps[0]) else None
                 for prev, m in zip(members, members[1:])]
        fit = MetricFit(clips, pre, T_BC, noise=self.noise, gravity_norm=self.G, bg_sigma=bg_sigma, scale_links=links,
                        estimate_walk=self.visual_drift, estimate_levels=self.noise_levels)
        fit.imu_level, fit.visual_level = (float(x) for x in self.levels)
        R0 = [pre.R[b.first] for b in fit.blocks]
        lam = np.array([m.lam for m in members])
        known = np.isfinite(lam) & (lam > 0)
        state = fit.initial_state(R0[0] @ members[0].g, starting_scales(lam, links))
        state.v[known] = np.stack([R @ m.v for R, m in zip(R0, members)])[known]
        priors = (self.prior,) if self.prior is not None else ()
        result = fit.solve(state, priors=priors)
        return Solution(members, fit, result, priors)

    def commit(self, sol: Solution) -> None:
        """Make ``sol`` the window: update every member's estimates, then marginalise the members that started more
        than ``window_s`` before the newest one (and as many as the next fit needs to stay within ``max_clips``)
        into the prior."""
        s = sol.result.state
        if self.noise_levels:
            self._learn_levels(sol)
        for k, m in enumerate(sol.members):
            g, v = sol.frame_state(k)
            m.lam, m.v, m.g = float(s.lam[k]), v, g
        t_new = float(sol.members[-1].stamps[0])
        drop = sum(1 for m in sol.members[:-1] if float(m.stamps[0]) < t_new - self.window_s)
        drop = max(drop, len(sol.members) - (self.max_clips - 1))
        mean, cov = sol.result.marginal(len(sol.members) - 1)
        self.ba = (mean[PriorLayout.ba], cov[PriorLayout.ba, PriorLayout.ba])
        self.members = sol.members[drop:]
        if drop > 0:
            self.prior = marginalise(sol.fit, sol.result, drop, sol.priors)

    def _learn_levels(self, sol: Solution) -> None:
        """One step of a recursive Fisher scoring of the noise levels over the flight: the new clip's share (1 / K of a
        window of K, each clip being in about K windows) of the fit's restricted-likelihood score and information
        in their logarithms (``FitResult.level_score``) joins what earlier clips gave, and the levels move by the
        score over all the information, which starts at the prior's (a heuristic share: while the window fills, a
        clip counts more than once). A single window's estimate swings by factors of
        ten between consecutive clips (two variances from a few hundred rows that both explain the same residuals);
        the flight's converges, as a sensor's constant noise should."""
        res = sol.result
        share = 1.0 / len(sol.members)
        info = self.level_info + share * res.level_info
        step = np.linalg.solve(info, share * res.level_score)  # info: the prior's plus Fisher informations
        if np.all(np.isfinite(step)):
            self.level_info = info
            self.levels = self.levels * np.exp(np.clip(step, -LEVEL_STEP, LEVEL_STEP))



__all__ = ["Member", "Solution", "Window", "members_span", "starting_scales"]
