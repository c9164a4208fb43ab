"""``OnlineOptions``: the knobs of the metric state carried across clips (window, marginal prior, consistency test,
bridges, restarts). The error model itself is ``InitOptions``' (the same for a clip on its own and in the window)."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class OnlineOptions:
    """The online window (``vi3_core.online.window``) and the odom chaining.

    window_s: s; clips starting within this time before the newest clip are fitted jointly with it; older ones are
        marginalised into a prior on gravity, the biases and the velocity, so their evidence is kept;
    max_clips: at most this many clips in the window (overlapping clips: hop < clip span);
    max_bridge_s: s; the longest time between consecutive clips that the IMU bridges (clips a busy worker dropped);
        the IMU of that span is kept (``imu_keep_s``), and the clip buffer keeps that much IMU history. A longer gap
        or missing IMU restarts the window (biases survive, widened by their random walk);
    max_bridge_sigma_m: m; a clip placed in odom through a bridge whose position 1-sigma exceeds this starts a new
        segment of the odom trajectory (the placement is the IMU's best guess, but not continuous in any useful sense);
    consistency_p: a clip whose whitened residual in the window (its positions and its velocity tie) has a chi-square
        tail probability below this is inconsistent with the window: rejected and named, the window unchanged;
    max_rejects: that many inconsistent clips in a row restart the window from the current clip;
    bg_window_s: s; the gyro-bias prior is the median of the clips' own (rotation-based) estimates of this long.
    """

    window_s: float = 7.0
    max_clips: int = 12
    max_bridge_s: float = 60.0
    max_bridge_sigma_m: float = 1.0
    consistency_p: float = 1e-3
    max_rejects: int = 3
    bg_window_s: float = 20.0

    def __post_init__(self) -> None:
        positive = ("window_s", "max_clips", "max_bridge_s", "max_bridge_sigma_m", "consistency_p", "max_rejects",
                    "bg_window_s")
        bad = [name for name in positive if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0)]
        if bad or not self.consistency_p < 1.0 or self.max_clips < 2:
            raise ValueError(f"OnlineOptions: {', '.join(bad) or 'consistency_p < 1, max_clips >= 2'} violated by "
                             f"{self}")

    @property
    def imu_keep_s(self) -> float:
        """s of IMU the estimator keeps: a window plus the longest bridge before it."""
        return self.window_s + self.max_bridge_s + 1.0
