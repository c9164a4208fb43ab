"""``InitOptions``: every knob of the GT-free inertial initialisation, in one place (like OpenVINS'
``InertialInitializerOptions``), filled from ROS parameters, the CLI or code."""

from __future__ import annotations

from dataclasses import dataclass

GRAVITY_NORM = 9.81


@dataclass(frozen=True)
class InitOptions:
    """Options of ``vi3_core.init.initialise``. Defaults follow the paper unless marked "beyond the paper".

    Scale and initial velocity
        scale_solver: "tls" (Eq. S, the paper) or "ols" (ablation: regression-diluted).
        v1_method: "all_pairs" (Eq. v0, median back-projection, the paper) or "first_pair" (ablation).
    Gyroscope bias
        bg_refine_iters: Gauss-Newton refinements of Eq. bg's estimate over all frame pairs (beyond the paper:
            Eq. bg averages consecutive pairs, whose visual noise telescopes to the two end frames; the
            all-pairs fit weighs every frame and removes the small-angle approximation). 0 = paper only.
    Gravity
        use_consensus: apply the consensus guard (Eq. guard) to an external seed; False adopts the seed as is.
        gamma_min_deg: noise floor of the guard (paper: 20 deg).
        seed_priority: order in which external seeds are tried (the first that passes the guard wins).
        fp_tol_deg, fp_max_iters: convergence tolerance and cap (evaluations) of the fixed point s = S(g),
            g = g_ls(s). The paper says 2-3 iterations; from the inertial seed the plain iteration contracts by
            only 0.65-0.999 per step on EuRoC-like motion, so it runs to the tolerance.
        fp_accelerate: Steffensen acceleration of that iteration (same fixed point; beyond the paper).
    Observability (beyond the paper: the paper's Sec. Limitations, made explicit as a status)
        min_accel_rms: m/s^2, RMS of the gravity-free body acceleration seen by the velocity increments;
            below it scale is unobservable (hover, constant velocity, pure rotation, stationary).
        min_alignment: minimum cosine between visual and inertial velocity increments.
        min_parallax: minimum ratio of the visual baseline to the median scene depth (scale-free).
    Data validation (status "rejected")
        max_imu_gap_s: largest allowed gap between consecutive IMU samples inside the clip.
        min_samples_per_interval: IMU samples needed between consecutive frames.
    """

    scale_solver: str = "tls"
    v1_method: str = "all_pairs"
    bg_refine_iters: int = 3
    use_consensus: bool = True
    gamma_min_deg: float = 20.0
    seed_priority: tuple[str, ...] = ("orientation", "geocalib", "long_window")
    fp_tol_deg: float = 1e-6
    fp_max_iters: int = 200
    fp_accelerate: bool = True
    min_accel_rms: float = 0.15
    min_alignment: float = 0.3
    min_parallax: float = 0.01
    max_imu_gap_s: float = 0.05
    min_samples_per_interval: int = 2
    gravity_norm: float = GRAVITY_NORM

    def __post_init__(self) -> None:
        if self.scale_solver not in ("tls", "ols"):
            raise ValueError(f"scale_solver must be 'tls' or 'ols', got {self.scale_solver!r}")
        if self.v1_method not in ("all_pairs", "first_pair"):
            raise ValueError(f"v1_method must be 'all_pairs' or 'first_pair', got {self.v1_method!r}")
        if self.fp_max_iters < 1 or self.bg_refine_iters < 0:
            raise ValueError("fp_max_iters must be >= 1 and bg_refine_iters >= 0")
