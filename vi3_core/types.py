"""The data types shared by every layer (see DESIGN.md, "Data types"). One definition of each.

Frames and units: SI, REP-103. ``B`` is the IMU (body) frame, ``C`` the camera frame with OpenCV optical
axes (x right, y down, z forward), ``W`` a world frame (ground truth only). ``B1``/``C1`` are the body and
camera frames at the first frame of a clip. Stamps are float64 seconds. Transforms ``T_XY`` are [4,4]
homogeneous matrices that map points from frame Y to frame X (the pose of Y in X).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

from vi3_core.errors import DataError


def _f64(a, shape_tail: tuple[int, ...], name: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.shape[arr.ndim - len(shape_tail):] != shape_tail or arr.ndim != len(shape_tail) + 1:
        raise DataError(f"{name}: expected shape [N,{','.join(map(str, shape_tail))}], got {arr.shape}")
    return arr


def window_bounds(t: np.ndarray, t0: float, t1: float, margin: int) -> tuple[int, int]:
    """[i0, i1) into sorted stamps ``t`` of the IMU window of [t0, t1]: the samples with t0 <= t <= t1 plus
    ``margin`` samples on each side where they exist. The one rule of every clip's IMU (evaluation and the node's
    clip buffer): the window covers the clip when ``t[i0] <= t0`` and ``t[i1 - 1] >= t1``, so a sample exactly at
    the first (last) frame is enough."""
    i0 = max(int(np.searchsorted(t, t0, side="left")) - margin, 0)
    i1 = min(int(np.searchsorted(t, t1, side="right")) + margin, len(t))
    return i0, i1


@dataclass(frozen=True)
class ImuSamples:
    """IMU samples in the body frame B.

    t: [M] float64 s, gyro: [M,3] rad/s, accel: [M,3] m/s^2 (specific force, so +9.81 up at rest).
    orientation: optional [M,4] quaternion (x, y, z, w) of B in a gravity-aligned world frame (z up), as
    reported in ``sensor_msgs/Imu.orientation`` by many flight controllers; NaN rows where absent.
    t_ns: optional [M] int64, the stamps as they came (integer ns), where they came as ns: float64 at epoch magnitudes
    resolves only ~0.24 us, so time differences that are compared with a limit use these (``validate.check_imu``).
    Construction does not validate values (NaN, gaps, order): ``vi3_core.init.validate_imu`` does, so that
    bad data becomes a status rather than an exception.
    """

    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    orientation: np.ndarray | None = None
    t_ns: np.ndarray | None = None

    def __post_init__(self) -> None:
        t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        object.__setattr__(self, "t", t)
        if self.t_ns is not None:
            object.__setattr__(self, "t_ns", np.asarray(self.t_ns, dtype=np.int64).reshape(-1))
        object.__setattr__(self, "gyro", _f64(self.gyro, (3,), "ImuSamples.gyro"))
        object.__setattr__(self, "accel", _f64(self.accel, (3,), "ImuSamples.accel"))
        if self.orientation is not None:
            object.__setattr__(self, "orientation", _f64(self.orientation, (4,), "ImuSamples.orientation"))
        for name in ("gyro", "accel", "orientation", "t_ns"):
            rows = getattr(self, name)
            if rows is not None and len(rows) != len(t):
                raise DataError(f"ImuSamples.{name} has {len(rows)} rows for {len(t)} stamps")

    def __len__(self) -> int:
        return len(self.t)

    def window(self, t0: float, t1: float, margin: int = 1) -> ImuSamples:
        """Samples with t0 <= t <= t1, plus ``margin`` samples on each side (for edge interpolation): see
        ``window_bounds``."""
        return self.select(slice(*window_bounds(self.t, t0, t1, margin)))

    def covers(self, t0: float, t1: float) -> bool:
        """Whether the samples cover [t0, t1] as a clip needs: one at or before t0 and one at or after t1
        (``window_bounds``)."""
        return len(self.t) > 0 and self.t[0] <= t0 and self.t[-1] >= t1

    def shifted(self, dt: float) -> ImuSamples:
        """The samples with their stamps moved by ``dt`` s (onto another clock; ``t_ns`` by dt rounded to ns)."""
        t_ns = None if self.t_ns is None else self.t_ns + round(dt * 1e9)
        return ImuSamples(self.t + dt, self.gyro, self.accel, self.orientation, t_ns)

    def read_through(self, A: np.ndarray) -> ImuSamples:
        """The samples with the accelerometer's calibration applied: accel = A [3,3] times the reading (its scale
        factors and cross-axis terms, e.g. ``vi3 reference --accel-intrinsics``)."""
        return ImuSamples(self.t, self.gyro, self.accel @ np.asarray(A, np.float64).T, self.orientation, self.t_ns)

    def select(self, idx) -> ImuSamples:
        """Rows ``idx`` (slice, index array or boolean mask)."""
        ori = None if self.orientation is None else self.orientation[idx]
        t_ns = None if self.t_ns is None else self.t_ns[idx]
        return ImuSamples(self.t[idx], self.gyro[idx], self.accel[idx], ori, t_ns)

    @staticmethod
    def concatenate(parts: list[ImuSamples]) -> ImuSamples:
        """Rows of ``parts`` in order; orientation and t_ns kept only if every part has them."""
        if not parts:
            return ImuSamples(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))

        def joined(name: str) -> np.ndarray | None:
            arrays = [getattr(p, name) for p in parts]
            return None if any(a is None for a in arrays) else np.concatenate(arrays)

        return ImuSamples(joined("t"), joined("gyro"), joined("accel"), joined("orientation"), joined("t_ns"))


@dataclass(frozen=True)
class GroundTruth:
    """Ground truth of a clip's n frames (EuRoC ``state_groundtruth_estimate0`` at the frame stamps).

    T_WB: [n,4,4] body pose in the world W (z up, gravity g_W = [0, 0, -9.81] unless stated);
    v_WB: [n,3] body velocity in W, m/s; bg, ba: [3] gyro (rad/s) and accel (m/s^2) biases;
    g_W: [3] gravity in W; depth: optional [n,H,W] z-depth in metres of the (undistorted) clip images, NaN
    where unknown.
    """

    T_WB: np.ndarray
    v_WB: np.ndarray
    bg: np.ndarray
    ba: np.ndarray
    g_W: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -9.81]))
    depth: np.ndarray | None = None


#: The default clip: frames per clip and the frame stride within it (the paper's n = 8 at stride 2, 0.7 s of 20 Hz
#: frames); the node's ``clip_length`` / ``stride`` parameters and the evaluation's clips take them from here.
CLIP_LENGTH = 8
CLIP_STRIDE = 2


@dataclass(frozen=True)
class Clip:
    """n synchronised frames and the IMU samples covering them.

    stamps: [n] float64 s (camera time, already corrected for the camera-IMU offset);
    images: [n,H,W] or [n,H,W,3] uint8 (RGB), undistorted; K: [3,3] intrinsics of the undistorted images;
    T_BC: [4,4] camera pose in the body frame (EuRoC ``T_BS`` of cam0); imu: samples covering
    [stamps[0], stamps[-1]] with at least one sample beyond each end; gt: optional ground truth;
    imu_history: optional longer IMU window around the clip (seconds), for the long-window gravity seed;
    stamps_ns: optional [n] int64, the frames' header stamps as recorded (camera time, ns), for outputs;
    imu_shift: s, how far the IMU's stamps (``imu``, ``imu_history``) were moved onto the frames' clock (minus the
    rig's applied time offset, ``RigEstimate.apply``); 0 as recorded.
    """

    stamps: np.ndarray
    images: np.ndarray
    K: np.ndarray
    T_BC: np.ndarray
    imu: ImuSamples
    gt: GroundTruth | None = None
    imu_history: ImuSamples | None = None
    stamps_ns: np.ndarray | None = None
    imu_shift: float = 0.0

    @property
    def n(self) -> int:
        return len(self.stamps)


@dataclass(frozen=True)
class UnitsLink:
    """A backbone's own word on how its units moved from one clip to the next, where its front end holds one scale
    across them (the ``classical`` backbone's keyframes): the units of this prediction over those of the clip that
    started at ``prev_start`` (s) and ended on this clip's first frame, log_ratio (log of (this clip's length of a
    thing) / (that clip's length of it)), and its 1-sigma (relative), the scale the front end may have lost between."""

    prev_start: float
    log_ratio: float
    sigma: float


@dataclass
class Geometry:
    """What a backbone predicts for a clip (numpy, detached).

    T_wc: [n,4,4] camera-to-world, OpenCV axes, world = first camera (T_wc[0] = I);
    K: [n,3,3] at the prediction resolution; depth: [n,h,w] z-depth (> 0, NaN/0 invalid);
    conf: [n,h,w] higher is better; metric: whether translation and depth are in metres; traj_depth_sigma: the
    1-sigma of the log of the trajectory's scale against the depth's, where the backbone knows how far the two can
    disagree (0: it does not say; the window then takes them at one scale); units_link: the backbone's ``UnitsLink``
    to the clip before, where it has one.
    """

    T_wc: np.ndarray
    K: np.ndarray
    depth: np.ndarray
    conf: np.ndarray
    metric: bool = False
    traj_depth_sigma: float = 0.0
    units_link: UnitsLink | None = None

    @property
    def n(self) -> int:
        return len(self.T_wc)

    def scaled(self, s: float) -> Geometry:
        """Translation and depth multiplied by ``s`` (rotation and intrinsics untouched; no ``units_link``: the units
        are no longer the backbone's)."""
        T = self.T_wc.copy()
        T[:, :3, 3] *= s
        return Geometry(T, self.K.copy(), self.depth * s, self.conf.copy(), self.metric, self.traj_depth_sigma)


class InitStatus(str, enum.Enum):
    """Outcome of the inertial initialisation."""

    OK = "ok"
    UNOBSERVABLE = "unobservable"  # too little translation/acceleration: scale cannot be claimed
    REJECTED = "rejected"  # bad data: NaN/Inf, too few samples, gaps, non-monotonic stamps


@dataclass
class ImuTrajectory:
    """Metric IMU-propagated states at the clip's n frames, origin at the first body frame B1.

    R: [n,3,3] R_B1Bi; p: [n,3] body positions in B1, m; v: [n,3] body velocities in B1, m/s;
    T_wc: [n,4,4] camera poses in the first camera frame C1 (T_C1Ci = T_CB T_B1Bi T_BC), metric.
    """

    R: np.ndarray
    p: np.ndarray
    v: np.ndarray
    T_wc: np.ndarray


@dataclass(frozen=True)
class ScaleFit:
    """What the error-model fit (``vi3_core.fit``) found for a clip, typed for the stages after the initialisation.

    lam: 1 / scale, model units per metre (as fitted, also when it is not positive); scale_rel_sigma: relative 1-sigma
    of the scale (inf: the data do not determine it); v1 [3] m/s: first-frame body velocity in B1; v1_sigma (m/s) and
    g_sigma (rad): the largest 1-sigma of v1 (any axis) and of gravity's direction; sigma_v: the clip's own visual
    noise per axis, model units; dof: the clip's residual degrees of freedom; variance_factor: the fit's a-posteriori
    variance factor (>= 1); settled: the clip's scale has settled (``FitResult.settled``: the Gauss-Newton step still
    to go moves it by at most a quarter of its linearised sigma; a scale is claimed only where it has); window_clips:
    clips fitted jointly (1: the clip on its own); time_offset, time_offset_sigma: s, the camera-IMU time offset left
    over after the configured one (a frame at t shows the body at t + time_offset) and its 1-sigma."""

    lam: float
    scale_rel_sigma: float
    v1: np.ndarray
    v1_sigma: float
    g_sigma: float
    sigma_v: float
    dof: float
    variance_factor: float
    settled: bool
    window_clips: int = 1
    time_offset: float = 0.0
    time_offset_sigma: float = float("nan")

    @property
    def sigma_v_m(self) -> float:
        """The visual noise in metres (NaN without a positive scale)."""
        return self.sigma_v / self.lam if self.lam > 0 else float("nan")


@dataclass
class InitResult:
    """GT-free inertial initialisation of one clip (paper Sec. "Inertial state initialization").

    bg: [3] gyro bias rad/s; g: [3] gravity in B1, m/s^2; scale: s with metric = s * model translation;
    scale_sigma: absolute 1-sigma of ``scale`` (same units; NaN when no error model produced it, inf when the data
    do not determine the scale; ``scale_sigma / scale`` is the relative error the evaluation checks against the
    truth); ba: [3] accelerometer bias m/s^2 (zeros where not estimated);
    v1: [3] body velocity at the first frame in B1, m/s; gravity_source: which estimate was adopted;
    consensus_deg: angle between the fixed points of the seeds (Eq. guard), NaN with a single seed;
    status/reason: see ``InitStatus``; target: the metric IMU trajectory (None unless status is ok); fit: the
    error-model fit behind the scale (None for the paper's solvers and before a fit ran); diagnostics: values for
    reports only (no later stage reads them).
    """

    status: InitStatus
    reason: str
    bg: np.ndarray = field(default_factory=lambda: np.zeros(3))
    g: np.ndarray = field(default_factory=lambda: np.array([np.nan] * 3))
    scale: float = float("nan")
    scale_sigma: float = float("nan")
    ba: np.ndarray = field(default_factory=lambda: np.zeros(3))
    v1: np.ndarray = field(default_factory=lambda: np.array([np.nan] * 3))
    gravity_source: str = ""
    consensus_deg: float = float("nan")
    iterations: int = 0
    target: ImuTrajectory | None = None
    fit: ScaleFit | None = None
    diagnostics: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.status is InitStatus.OK


@dataclass
class AnchorResult:
    """Output of ``vi3_core.anchor.anchor`` for one clip.

    geometry: metric Geometry (or the base geometry, unscaled, when the init is not ok);
    base: the backbone's unanchored Geometry; mode: the anchoring mode that actually ran
    ("init" | "cond" | "ttr" | "none"); alpha: final TTR scale (or the init scale);
    losses: per-step dict of loss arrays (TTR), alphas: [K] alpha trajectory; timings: seconds per stage.
    """

    geometry: Geometry
    base: Geometry
    init: InitResult
    mode: str
    alpha: float
    target: ImuTrajectory | None = None
    losses: dict[str, np.ndarray] = field(default_factory=dict)
    alphas: np.ndarray = field(default_factory=lambda: np.zeros(0))
    timings: dict[str, float] = field(default_factory=dict)
    status: str = ""
