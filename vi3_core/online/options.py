"""``OnlineOptions``: the knobs of the metric state carried across clips (priors, consistency tests, reset)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class OnlineOptions:
    """Priors carried from clip to clip and the thresholds of their consistency tests.

    max_gap_s: s; a longer time between the previous clip's nearest frame and this clip's first frame resets the
        state (the clip falls back to the GT-free initialisation);
    bg_gain: weight of each clip's own gyro-bias estimate in the filtered bias (0: never updated, 1: no filter);
    gravity_gain: weight of each clip's own gravity estimate when it refines the gravity prior;
    gravity_tol_deg: the gravity prior is dropped when it is farther than this from the clip's own estimate;
    residual_ratio, residual_floor_m: a prior is dropped when the position residual with it exceeds
        max(residual_ratio * the residual without it, residual_floor_m), metres (gravity: the free (s, v1) position
        fit with the prior against the one with the clip's own gravity; velocity: v1 held at the prior against the
        free (s, v1) fit);
    scale_ratio: the velocity prior is dropped when the scale it implies differs from the free position fit's by
        more than this factor (either way);
    v1_weight_s: s; weight of the velocity prior against the positions in the final fit (Tikhonov term);
    imu_keep_s: s of IMU kept for the bridges between clips.
    """

    max_gap_s: float = 1.0
    bg_gain: float = 0.2
    gravity_gain: float = 0.1
    gravity_tol_deg: float = 30.0
    residual_ratio: float = 4.0
    residual_floor_m: float = 0.03
    scale_ratio: float = 2.0
    v1_weight_s: float = 0.05
    imu_keep_s: float = 5.0

    def __post_init__(self) -> None:
        for name in ("bg_gain", "gravity_gain"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"OnlineOptions.{name} must be in [0, 1], got {getattr(self, name)}")
        if self.scale_ratio <= 1.0 or self.residual_ratio <= 0.0 or self.max_gap_s <= 0.0 or self.imu_keep_s <= 0.0:
            raise ValueError("OnlineOptions: scale_ratio must be > 1; residual_ratio, max_gap_s and imu_keep_s > 0")
