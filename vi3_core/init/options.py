"""``InitOptions``: every knob of the GT-free inertial initialisation, in one place (like OpenVINS'
``InertialInitializerOptions``), filled from ROS parameters, the CLI or code."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vi3_core.fit.noise import ImuNoiseModel

GRAVITY_NORM = 9.81
SCALE_SOLVERS = ("eiv", "tls", "ols")


@dataclass(frozen=True)
class InitOptions:
    """Options of ``vi3_core.init.initialise``. Defaults follow the paper unless marked "beyond the paper".

    Scale and initial velocity
        scale_solver: "eiv" (default, beyond the paper: the backbone positions regressed on the IMU kinematics with
            an error model, ``vi3_core.fit``; s, g, v1, ba and bg are refined jointly from the paper's solution and the
            scale gets its standard deviation), "tls" (Eq. S and Eq. v0, the paper) or "ols" (ablation: regression-
            diluted). The paper's solvers carry no error model: their scale_sigma is NaN.
        v1_method: for "tls"/"ols": "all_pairs" (Eq. v0, median back-projection, the paper) or "first_pair".
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
    Error model and observability (beyond the paper: the paper's Sec. Limitations, made explicit as a status)
        accel_noise_density, gyro_noise_density, gyro_scale_error, accel_bias_sigma, gyro_bias_sigma,
            scale_rel_floor, accel_bias_walk, gyro_bias_walk, time_offset_sigma: the IMU error model of the "eiv" fit
            (``ImuNoiseModel``; scale_rel_floor is its ``rel_floor``; time_offset_sigma, s, how far the configured
            camera-IMU time offset may be off: the fit estimates the rest and widens the scale's sigma by it).
        accel_matrix: the accelerometer's calibration, 9 numbers row-major (commas or spaces), the specific force
            being this matrix times the reading (scale factors, cross-axis terms: ``vi3 reference
            --accel-intrinsics``, Kalibr's or the IMU maker's calibration); "" for none. Applied to every clip's IMU
            (``StreamEstimator``) and the node's IMU-rate odometry.
        visual_drift: the online window estimates a random walk of the backbone's positions (temporally correlated
            errors: a scale drifting inside a clip, a depth-dependent bias) beside each clip's white noise, from the
            residuals of all its clips, and widens the scales' sigmas by it.
        noise_levels: the online window estimates the IMU's noise level (a factor on the noise model's position
            covariance) and the clips' visual noise level from the residuals of all its clips, and fits the scales
            by errors in variables (``MetricFit`` with estimate_levels).
        max_scale_sigma: a scale whose relative 1-sigma exceeds this is not claimed (status unobservable). At 4 %
            a claimed scale 10 % off is a 2.5-sigma event (about 1 % of the claims at the limit, fewer below it).
        max_rotation_error: a clip whose backbone relative rotations disagree with the bias-corrected gyro by more
            than this (worst frame pair, degrees) is a backbone failure: status rejected, before any scale.
        min_accel_rms: m/s^2, RMS of the gravity-free body acceleration seen by the velocity increments;
            below it scale is unobservable (hover, constant velocity, pure rotation, stationary).
        min_alignment: for "tls"/"ols": minimum cosine between visual and inertial velocity increments.
        min_parallax: minimum ratio of the visual baseline to the median scene depth (scale-free).
    Data validation (status "rejected")
        max_imu_gap: largest allowed gap between consecutive IMU samples inside the clip.
        min_samples_per_interval: IMU samples needed between consecutive frames.
    """

    scale_solver: str = "eiv"
    v1_method: str = "all_pairs"
    bg_refine_iters: int = 3
    use_consensus: bool = True
    gamma_min_deg: float = 20.0
    seed_priority: tuple[str, ...] = ("orientation", "geocalib", "long_window")
    fp_tol_deg: float = 1e-6
    fp_max_iters: int = 200
    fp_accelerate: bool = True
    accel_noise_density: float = ImuNoiseModel.accel_noise_density
    gyro_noise_density: float = ImuNoiseModel.gyro_noise_density
    gyro_scale_error: float = ImuNoiseModel.gyro_scale_error
    accel_bias_sigma: float = ImuNoiseModel.accel_bias_sigma
    gyro_bias_sigma: float = ImuNoiseModel.gyro_bias_sigma
    scale_rel_floor: float = ImuNoiseModel.rel_floor
    accel_bias_walk: float = ImuNoiseModel.accel_bias_walk
    gyro_bias_walk: float = ImuNoiseModel.gyro_bias_walk
    time_offset_sigma: float = ImuNoiseModel.time_offset_sigma
    accel_matrix: str = ""
    visual_drift: bool = True
    noise_levels: bool = False
    max_scale_sigma: float = 0.04
    max_rotation_error: float = 2.0
    min_accel_rms: float = 0.15
    min_alignment: float = 0.3
    min_parallax: float = 0.01
    max_imu_gap: float = 0.05
    min_samples_per_interval: int = 2
    gravity_norm: float = GRAVITY_NORM

    def __post_init__(self) -> None:
        if self.scale_solver not in SCALE_SOLVERS:
            raise ValueError(f"scale_solver must be one of {', '.join(SCALE_SOLVERS)}; got {self.scale_solver!r}")
        if self.v1_method not in ("all_pairs", "first_pair"):
            raise ValueError(f"v1_method must be 'all_pairs' or 'first_pair', got {self.v1_method!r}")
        if self.fp_max_iters < 1 or self.bg_refine_iters < 0:
            raise ValueError("fp_max_iters must be >= 1 and bg_refine_iters >= 0")
        if not (self.max_scale_sigma > 0 and self.max_rotation_error > 0):
            raise ValueError("max_scale_sigma and max_rotation_error must be > 0")
        _ = self.noise_model  # validates the error model's values
        _ = self.accel_A  # validates the accelerometer's matrix

    @property
    def accel_A(self) -> np.ndarray | None:
        """[3,3] ``accel_matrix`` (specific force = A times the accelerometer's reading), None for the identity."""
        text = self.accel_matrix.replace(",", " ").split()
        if not text:
            return None
        try:
            A = np.array([float(x) for x in text]).reshape(3, 3)
        except ValueError:
            raise ValueError(f"accel_matrix must be 9 numbers (row-major, specific force = A x reading), "
                             f"got {self.accel_matrix!r}") from None
        if not np.isfinite(A).all() or not 0.5 < np.linalg.det(A) < 2.0 or np.abs(A - np.eye(3)).max() > 0.5:
            raise ValueError(f"accel_matrix {self.accel_matrix!r} is no accelerometer calibration (finite, within 0.5 "
                             "of the identity, determinant in (0.5, 2))")
        return None if np.array_equal(A, np.eye(3)) else A

    @property
    def noise_model(self) -> ImuNoiseModel:
        """The IMU error model of the "eiv" fit."""
        return ImuNoiseModel(accel_noise_density=self.accel_noise_density, gyro_noise_density=self.gyro_noise_density,
                             gyro_scale_error=self.gyro_scale_error, accel_bias_sigma=self.accel_bias_sigma,
                             gyro_bias_sigma=self.gyro_bias_sigma, rel_floor=self.scale_rel_floor,
                             accel_bias_walk=self.accel_bias_walk, gyro_bias_walk=self.gyro_bias_walk,
                             time_offset_sigma=self.time_offset_sigma)
