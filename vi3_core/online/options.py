"""``OnlineOptions``: the knobs of the metric state carried across clips (window, marginal prior, consistency test,
bridges, restarts). The error model itself is ``InitOptions``' (the same for a clip on its own and in the window)."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class OnlineOptions:
    """The online window (``vi3_core.online.window``) and the odom chaining.

    online_window: s; clips starting within this time before the newest clip are fitted jointly with it; older ones are
        marginalised into a prior on gravity, the biases and the velocity, so their evidence is kept;
    online_max_clips: at most this many clips in the window (overlapping clips: hop < clip span);
    online_max_bridge: s; the longest time between consecutive clips that the IMU bridges (clips a busy worker dropped);
        the IMU of that span is kept (``imu_keep_s``), and the clip buffer keeps that much IMU history. A longer gap
        or missing IMU restarts the window (biases survive, widened by their random walk);
    online_max_bridge_sigma: m; a clip placed in odom through a bridge whose position 1-sigma exceeds this starts a new
        segment of the odom trajectory (the placement is the IMU's best guess, but not continuous in any useful sense);
    odom_max_scale_sigma: a clip whose scale the claim gate (``max_scale_sigma``) refuses is placed in odom all the
        same where the window's fit of it settled on a positive scale known to this relative 1-sigma
        (``chain.OdomChain.places_unclaimed``): the odometry goes on through such stretches at the window's scale, its
        uncertainty counting the sigma, where the IMU alone would bridge them; nothing else of the clip is published
        (at or below ``max_scale_sigma``, 0 for one: only claimed clips are placed);
    online_consistency_p: a clip whose whitened residual in the window (its positions and its velocity tie) has a
        chi-square tail probability below this, or whose own scale disagrees with the window's at this level
        (``estimator.scale_agreement``), is inconsistent with the window: rejected and named, the window unchanged;
    online_max_rejects: that many inconsistent clips in a row restart the window from the current clip;
    online_bg_window: s; the gyro-bias prior is the median of the clips' own (rotation-based) estimates of this long;
    shared_frames: each clip starts with the last this many frames of the clip before it that joined the window, so
        the two are linked by a scale ratio measured on the shared frames (``vi3_core.online.link``); they count in
        the clip's length (the node's clips then start every (clip_length - shared_frames) * stride frames); 0: no
        links, every clip's scale tied to the others through the IMU only;
    shared_max_gap: s; the shared frames replace the first ones of a clip that does not start with them (clips a busy
        worker dropped in between) when they end at most this long before the clip's own frames, so the clip is
        linked across the drop; 0 (default): never, such a clip is not linked. For a backbone that registers views
        seconds apart: the embedded ``classical`` one does not (its tracks break, the clip fails its rotation check),
        and with it this costs claims and drift;
    link_sigma_floor: relative 1-sigma added to every link for what the spread of its depth blocks cannot show.
    """

    online_window: float = 7.0
    online_max_clips: int = 12
    online_max_bridge: float = 60.0
    online_max_bridge_sigma: float = 1.0
    odom_max_scale_sigma: float = 0.1
    online_consistency_p: float = 1e-3
    online_max_rejects: int = 3
    online_bg_window: float = 20.0
    shared_frames: int = 1
    shared_max_gap: float = 0.0
    link_sigma_floor: float = 0.005

    def __post_init__(self) -> None:
        positive = ("online_window", "online_max_clips", "online_max_bridge", "online_max_bridge_sigma",
                    "online_consistency_p", "online_max_rejects", "online_bg_window")
        bad = [name for name in positive if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0)]
        bad += [name for name in ("shared_frames", "shared_max_gap", "link_sigma_floor", "odom_max_scale_sigma")
                if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0)]
        if bad or not self.online_consistency_p < 1.0 or self.online_max_clips < 2:
            raise ValueError(f"OnlineOptions: {', '.join(bad) or 'online_consistency_p < 1, online_max_clips >= 2'} "
                             f"violated by {self}")

    def clip_hop(self, clip_length: int, stride: int) -> int:
        """Input frames between clip starts when none is set: (clip_length - shared_frames) * stride, so each clip
        starts with the last shared_frames frames of the one before."""
        return (clip_length - self.shared_frames) * stride

    @property
    def imu_keep_s(self) -> float:
        """s of IMU the estimator keeps: a window plus the longest bridge before it."""
        return self.online_window + self.online_max_bridge + 1.0
