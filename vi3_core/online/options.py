"""``OnlineOptions``: the knobs of the metric state carried across clips (window, priors, consistency tests, reset)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class OnlineOptions:
    """The online window (``vi3_core.online.window``), the priors from the odom state and their tests.

    window_s: s; clips starting within this time before the current clip are fitted jointly with it;
    max_gap_s: s; a longer time between the previous clip's last frame and this clip's first frame restarts the window
        (the clip falls back to the GT-free initialisation); shorter gaps (clips dropped by a busy worker) are
        bridged by the IMU, with looser velocity ties;
    ba_weight: weight of the zero-accelerometer-bias prior row (m of position per m/s^2 of bias): small, so that
        a real bias (EuRoC's reach 0.1-0.2 m/s^2) is estimated, yet ba stays determined when the window does not
        rotate (1.0 held a 0.15 m/s^2 bias near zero and shifted the scales by several per cent);
    velocity_link_s: weight of the IMU tie between consecutive clips' velocities (m of position per m/s), for clips
        0.8 s apart (``window.LINK_NOMINAL_S``; scaled by sqrt(0.8 s / their spacing));
    residual_ratio, residual_floor_m: a new clip is inconsistent with the window when a clip's position residual
        exceeds max(residual_ratio * the median residual of the last accepted window, residual_floor_m), metres;
    max_rejects: that many inconsistent clips in a row restart the window from the current clip;
    gravity_tol_deg, velocity_tol_mps: the odom state's gravity (deg) and velocity (m/s) at the clip's first frame,
        propagated through the IMU, are dropped as priors when they differ from the window's own estimate by more;
    gravity_weight_s2, v1_weight_s: weights of the accepted priors' rows (s^2, s: a position-equivalent metre);
    max_scale_rel_sigma: a clip whose scale has a larger relative 1-sigma over the window is unobservable;
    bg_window_s: s; the gyro bias is the median of the own estimates of the clips of this long;
    imu_keep_s: s of IMU kept for the window and the bridges between clips (> window_s).
    """

    window_s: float = 7.0
    max_gap_s: float = 3.0
    ba_weight: float = 0.01
    velocity_link_s: float = 0.05
    residual_ratio: float = 4.0
    residual_floor_m: float = 0.01
    max_rejects: int = 3
    gravity_tol_deg: float = 2.0
    velocity_tol_mps: float = 0.25
    gravity_weight_s2: float = 0.02
    v1_weight_s: float = 0.05
    max_scale_rel_sigma: float = 0.05
    bg_window_s: float = 20.0
    imu_keep_s: float = 12.0

    def __post_init__(self) -> None:
        positive = ("window_s", "max_gap_s", "ba_weight", "velocity_link_s", "residual_ratio", "residual_floor_m",
                    "max_rejects", "gravity_tol_deg", "velocity_tol_mps", "max_scale_rel_sigma", "bg_window_s")
        bad = [name for name in positive if not getattr(self, name) > 0]
        bad += [name for name in ("gravity_weight_s2", "v1_weight_s") if not getattr(self, name) >= 0]
        if bad:
            raise ValueError(f"OnlineOptions: {', '.join(bad)} must be positive (weights >= 0)")
        if not self.imu_keep_s > self.window_s + self.max_gap_s:
            raise ValueError(f"OnlineOptions.imu_keep_s ({self.imu_keep_s}) must exceed window_s + max_gap_s")
