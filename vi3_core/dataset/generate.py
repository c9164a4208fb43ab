"""EuRoC-format ASL sequences with exact ground truth: a trajectory, its IMU, rendered cam0 frames and GT depth.

Generated (``SequenceSpec.from_euroc`` None): the drone flies ``make_trajectory("drone", seed, motion=...)`` inside
the scene's free volume; cam0 (EuRoC's intrinsics, radial-tangential distortion and ``T_BS``) renders mono8 at
20 Hz; the IMU (``ImuSimulator``: EuRoC noise, airframe vibration for the realistic presets, a random initial gyro
bias and, by default, an accelerometer bias of EuRoC's size) and the ground-truth state run at 200 Hz on the same
nanosecond grid, so camera stamps coincide with IMU and GT stamps, as in EuRoC.

Along a real EuRoC recording (``from_euroc``: a ``mav0`` folder with ``imu0``, ``state_groundtruth_estimate0`` and
``cam0/sensor.yaml``, images not needed): the IMU samples are carried unchanged (values and ns stamps); cam0 frames
are rendered at the camera's rate on the IMU's own ns stamps within the span both cover, except inside a GT gap (rows
more than ``MAX_GT_GAP_NS`` apart), at the GT body pose (position: cubic Hermite through the GT positions and
velocities; attitude: rotation spline) times the folder's own cam0 ``T_BS``, in the scene moved and grown around the
trajectory; the GT rows are copied over the IMU's span and to the rows bracketing the first and last frames, so the
written GT covers every frame wherever the recording's GT starts or ends.

Everything is produced and written one ``BLOCK_NS`` of time at a time (frames rendered by a small thread pool,
two blocks in flight), so memory does not grow with the length of the sequence.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicHermiteSpline
from scipy.spatial.transform import Rotation, RotationSpline

from vi3_core import so3
from vi3_core.dataset import asl
from vi3_core.dataset.calib import CameraCalib, load_calib
from vi3_core.dataset.sequence import make_clip, sample_clips
from vi3_core.errors import DataError
from vi3_core.render.raycast import Renderer
from vi3_core.render.scene import SCENES, Scene, make_scene
from vi3_core.render.sensor import REALSENSE, Exposure, SensorModel, blur, finish
from vi3_core.rolling_shutter import row_times
from vi3_core.sim import euroc
from vi3_core.sim.imu import REALSENSE_NOISE, ImuNoise, ImuSimulator, default_vibration, draw_accel_bias
from vi3_core.sim.trajectory import MOTIONS, make_trajectory
from vi3_core.types import Clip, ImuSamples

#: EuRoC cam0 (MH_01 ``cam0/sensor.yaml``): intrinsics, radial-tangential distortion, T_BS, 752x480 @ 20 Hz.
EUROC_CAM0 = CameraCalib(K=euroc.K_cam0(), dist_model="radtan", dist=np.array(euroc.DISTORTION_CAM0),
                         size=euroc.RESOLUTION_CAM0, T_BC=euroc.T_BS_CAM0.copy(), rate_hz=euroc.CAMERA_RATE_HZ)
#: A RealSense colour stream at 1280x720 (the DM-VIO dataset's published pinhole intrinsics, no distortion), its IMU
#: a centimetre from the lens, mounted as EuRoC's cam0 is (the simulator's body axes).
_RS_T_BC = euroc.T_BS_CAM0.copy()
_RS_T_BC[:3, 3] = (-0.012, 0.002, 0.002)
REALSENSE_CAM = CameraCalib(K=np.array([[906.2598, 0.0, 642.8964], [0.0, 906.5510, 353.1422], [0.0, 0.0, 1.0]]),
                            dist_model="none", dist=np.zeros(0), size=(1280, 720), T_BC=_RS_T_BC, rate_hz=None)
#: camera models of ``SequenceSpec.camera``: EuRoC's global-shutter cam0 rendered ideally, or a RealSense with what
#: its sensor does (``vi3_core.render.sensor.REALSENSE``)
CAMERAS = ("euroc", "realsense")
#: The RealSense's IMU: its gyro and accelerometer streams merged by the driver (a base stream at 200.9 Hz, the other
#: stream's stamps inserted every ~9 samples at a drifting phase, values interpolated: 5 % of its intervals under
#: 1.5 ms, the shortest under a microsecond), its stamps this far behind the frames' (``vi3 calib`` on the recording:
#: -53 ms).
RS_IMU_PERIOD_NS, RS_MERGE_EVERY, RS_MERGE_DRIFT_NS = 4_977_000, 9, 236_000
RS_IMU_DELAY_NS = -53_000_000

T0_NS = 1_700_000_000_000_000_000  # first camera stamp (ns): EuRoC-like epoch stamps
CAM_PERIOD_NS = 50_000_000  # 20 Hz
IMU_PERIOD_NS = 5_000_000  # 200 Hz
IMU_MARGIN_NS = 100_000_000  # IMU and GT start 0.1 s before the first frame and end 0.1 s after the last
IMU_HISTORY_NS = 1_000_000_000  # IMU kept before the first frame of a recording rendered from a later start
#: Consecutive GT rows of a recording farther apart than this are a gap: no frame is rendered inside it (its pose would
#: be interpolated over motion nobody measured). EuRoC's GT rows are 5-10 ms apart (25 ms in the 40 Hz V1_02 excerpt).
MAX_GT_GAP_NS = 100_000_000
BLOCK_NS = 2_000_000_000  # streams are produced and written 2 s at a time
MIN_SECONDS = CAM_PERIOD_NS * 1e-9  # the shortest sequence: two frames
#: Version of what the generator writes for given parameters (part of the cache marker).
GENERATOR_VERSION = 3
#: Hidden folders that hold a sequence while it is written: ``.vi3-generating.<pid>.<random>``.
STAGING_PREFIX = ".vi3-generating."


@dataclass(frozen=True)
class SequenceSpec:
    """What to write. seconds: length of the camera stream (None with ``from_euroc``: all the recording covers);
    seed: scene, trajectory and IMU noise (scene only with ``from_euroc``); scene: one of ``SCENES``; motion: one of
    ``MOTIONS``; accel_bias: an initial accelerometer bias of EuRoC's size (else zero); imu_noise: EuRoC noise,
    bias random walks and airframe vibration (else noise-free IMU with constant biases); with_depth: GT depth maps;
    from_euroc: a real EuRoC ``mav0`` folder to follow (motion, accel_bias and imu_noise then do not apply);
    start_s: with ``from_euroc``, where the camera stream starts, seconds into the span IMU and GT both cover; camera:
    one of ``CAMERAS`` (generated sequences: ``realsense`` renders 1280x720 with a rolling shutter, motion blur, auto
    exposure and the frame rates it sets, lost frames and stalls, vignetting, noise and JPEG, and writes the RealSense's
    IMU: its noise, merged streams and a clock 53 ms off the frames'; the calibration written is the published one,
    which does not know that offset). Raises DataError on a value that cannot make a sequence."""

    seconds: float | None = 4.0
    seed: int = 0
    scene: str = "room"
    motion: str = "medium"
    accel_bias: bool = True
    imu_noise: bool = True
    with_depth: bool = True
    from_euroc: str | None = None
    start_s: float = 0.0
    camera: str = "euroc"

    def __post_init__(self) -> None:
        if self.seconds is None:
            if self.from_euroc is None:
                raise DataError("seconds is required for a generated sequence")
        elif not (isinstance(self.seconds, int | float) and math.isfinite(self.seconds)) \
                or self.seconds < MIN_SECONDS:
            raise DataError(f"seconds must be a finite number >= {MIN_SECONDS:g} (two camera frames), got "
                            f"{self.seconds!r}; nothing to generate")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int | np.integer) or self.seed < 0:
            raise DataError(f"seed must be an integer >= 0, got {self.seed!r}")
        if self.scene not in SCENES:
            raise DataError(f"unknown scene {self.scene!r}; choose one of {sorted(SCENES)}")
        if self.motion not in MOTIONS:
            raise DataError(f"unknown motion preset {self.motion!r}; choose one of {list(MOTIONS)}")
        if not (math.isfinite(self.start_s) and self.start_s >= 0.0):
            raise DataError(f"start must be a finite number of seconds >= 0, got {self.start_s!r}")
        if self.start_s and self.from_euroc is None:
            raise DataError("start applies to sequences rendered along a recording (from_euroc)")
        if self.camera not in CAMERAS:
            raise DataError(f"unknown camera {self.camera!r}; choose one of {list(CAMERAS)}")
        if self.camera != "euroc" and self.from_euroc is not None:
            raise DataError("a camera model other than euroc is for generated sequences (a recording keeps its own)")


@dataclass(frozen=True)
class Block:
    """The streams of one block of time, each in stamp order: frames ``cam_ns`` [n] int64 at camera poses ``T_WC``
    [n,4,4] with their raw mono8 ``images`` ([H,W] uint8 each; empty until rendered), IMU ``imu_ns`` [m] with
    ``imu``, ground truth ``gt_ns`` [k] with body poses ``T_WB`` [k,4,4] in W, ``v_WB`` [k,3], biases ``bg``,
    ``ba`` [k,3]; ``exposure`` [n, 2]: each frame's exposure (the share of the sensor's longest) and gain (None: an
    ideal camera)."""

    cam_ns: np.ndarray
    T_WC: np.ndarray
    imu_ns: np.ndarray
    imu: ImuSamples
    gt_ns: np.ndarray
    T_WB: np.ndarray
    v_WB: np.ndarray
    bg: np.ndarray
    ba: np.ndarray
    images: tuple[np.ndarray, ...] = ()
    exposure: np.ndarray | None = None


def euroc_mav0(path) -> Path:
    """The ``mav0`` folder at ``path`` or inside it (a recording to follow needs no images, so no cam0/data)."""
    path = Path(path)
    mav0 = path / "mav0" if (path / "mav0").is_dir() else path
    if not (mav0 / "imu0").is_dir():
        raise DataError(f"{path}: not an EuRoC mav0 folder (no imu0/ in it or in {path / 'mav0'})")
    return mav0


def _in(ns: np.ndarray, ns0: int, ns1: int) -> slice:
    """The rows of sorted stamps ``ns`` within [ns0, ns1)."""
    return slice(int(np.searchsorted(ns, ns0)), int(np.searchsorted(ns, ns1)))


@dataclass(frozen=True)
class Written:
    """What ``write_sequence`` wrote: ``calib``, the cam0 calibration the frames were rendered with, and ``gt_gaps``
    [G,2] int64 ns, the gaps in a followed recording's ground truth that frames were left out of (the stamps of the
    GT rows either side of each; none for a generated sequence)."""

    calib: CameraCalib
    gt_gaps: np.ndarray


class _Source:
    """What ``write_sequence`` renders along: ``renderer`` (set there) renders each frame ideally."""

    renderer: Renderer | None = None

    def render(self, ns: int, T_WC: np.ndarray, exposure: np.ndarray | None,
               with_depth: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """The frame at ``ns`` from camera pose ``T_WC`` [4,4] and its z-depth (``Renderer.render``)."""
        return self.renderer.render(T_WC, with_depth=with_depth)


class _Generated(_Source):
    """A generated flight (see the module docstring); ``block`` must be called on consecutive blocks."""

    gt_gaps = np.zeros((0, 2), dtype=np.int64)  # its GT is on the IMU's grid: no gaps

    def __init__(self, spec: SequenceSpec, world: Scene) -> None:
        realsense = spec.camera == "realsense"
        self.calib = REALSENSE_CAM if realsense else EUROC_CAM0
        self.sensor = REALSENSE if realsense else None
        self.traj = make_trajectory("drone", spec.seed, motion=spec.motion, center=tuple(world.center),
                                    extent=tuple(world.extent))
        if realsense:
            self.cam_ns, self.exposure = _realsense_frames(REALSENSE, spec.seconds, spec.seed)
        else:
            n_frames = int(round(spec.seconds * 1e9 / CAM_PERIOD_NS)) + 1
            self.cam_ns, self.exposure = T0_NS + np.arange(n_frames, dtype=np.int64) * CAM_PERIOD_NS, None
        self.last_frame_ns = int(self.cam_ns[-1])
        self.first_ns, self.last_ns = T0_NS - IMU_MARGIN_NS, self.last_frame_ns + IMU_MARGIN_NS
        self.imu_period_ns = RS_IMU_PERIOD_NS if realsense else IMU_PERIOD_NS
        self.imu_delay_ns = RS_IMU_DELAY_NS if realsense else 0
        rng = np.random.default_rng([spec.seed, 3])
        bg0 = rng.uniform(-0.03, 0.03, size=3)  # rad/s, EuRoC-sized initial gyro bias
        ba0 = draw_accel_bias(rng) if spec.accel_bias else np.zeros(3)
        self.noise = (REALSENSE_NOISE if realsense else ImuNoise()) if spec.imu_noise else ImuNoise.zero()
        self.imu = ImuSimulator(self.traj, dt=self.imu_period_ns * 1e-9, noise=self.noise, bg0=bg0, ba0=ba0,
                                seed=spec.seed, vibration=default_vibration(spec.motion, spec.imu_noise))
        self.seed = spec.seed

    def _t(self, ns: np.ndarray) -> np.ndarray:
        """The trajectory's clock: seconds since the first IMU sample (exact on the ns grid)."""
        return (ns - self.first_ns) * 1e-9

    def block(self, ns0: int, ns1: int) -> Block:
        p = self.imu_period_ns
        first = self.first_ns + -(-(max(ns0, self.first_ns) - self.first_ns) // p) * p  # on the IMU's own grid
        imu_ns = np.arange(first, min(ns1, self.last_ns + 1), p, dtype=np.int64)
        cam = (self.cam_ns >= ns0) & (self.cam_ns < ns1)
        cam_ns = self.cam_ns[cam]
        sim = self.imu(self._t(imu_ns))
        gyro, accel, stamps = sim.samples.gyro, sim.samples.accel, imu_ns
        if self.sensor is not None:  # the driver's merged streams, on the IMU's own clock
            stamps, gyro, accel = _merged(imu_ns, gyro, accel)
        written = stamps + self.imu_delay_ns
        return Block(cam_ns, self.traj.T_WB(self._t(cam_ns)) @ self.calib.T_BC, written,
                     ImuSamples(written * 1e-9, gyro, accel, t_ns=written), imu_ns,
                     self.traj.T_WB(self._t(imu_ns)), self.traj.velocity_W(self._t(imu_ns)), sim.bg, sim.ba,
                     exposure=None if self.exposure is None else self.exposure[cam])

    def render(self, ns: int, T_WC: np.ndarray, exposure: np.ndarray | None,
               with_depth: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """The stored frame at ``ns`` (camera pose ``T_WC`` at its middle row) and its z-depth: ideal, or through
        the sensor (each row at its own time, the exposure integrated, then ``render.sensor.finish``)."""
        if self.sensor is None:
            return super().render(ns, T_WC, exposure, with_depth)
        m = self.sensor
        H = self.calib.size[1]
        t_rows = row_times(self._t(np.array([ns]))[0], H, m.readout_s)
        rows = self.traj.T_WB(t_rows) @ self.calib.T_BC
        radiance, depth = self.renderer.radiance(rows)
        radiance = blur(radiance, depth, self.calib.K, rows, lambda t: self.traj.T_WB(t) @ self.calib.T_BC,
                        t_rows, exposure[0] * m.exposure_s, m.blur_samples)
        rng = np.random.default_rng([self.seed, int(ns % 2**62), 41])  # the frame's own noise, whatever the thread
        image = finish(radiance * np.float32(exposure[0]), float(exposure[1]), m, rng)
        depth = np.where(np.isfinite(depth), depth, np.nan).astype(np.float32) if with_depth else None
        return image, depth


def _realsense_frames(sensor: SensorModel, seconds: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The frame stamps [n] int64 ns of ``seconds`` of a camera whose auto exposure sets its rate (``Exposure``), with
    frames lost at random and stalls (``sensor.drop_rate``, ``gap_rate``), and each frame's (exposure, gain) [n,2]."""
    ae, rng = Exposure(sensor, seed), np.random.default_rng([seed, 13])
    t, stamps, exposure = 0.0, [], []
    interval = sensor.frame_intervals_s[0]
    while t <= seconds:
        interval, e, g = ae.next(sensor.target_grey, interval)
        if rng.random() < sensor.gap_rate * interval:
            t += rng.uniform(*sensor.gap_s)  # a stall: no frame
        elif rng.random() >= sensor.drop_rate:
            stamps.append(t)
            exposure.append((e, g))
        t += interval
    return T0_NS + np.round(np.array(stamps) * 1e9).astype(np.int64), np.array(exposure)


def _merged(base_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An IMU stream as a RealSense driver merges its gyro and accelerometer: the base stream ``base_ns`` [m] with a
    sample of the other inserted every ``RS_MERGE_EVERY`` samples at a phase drifting by ``RS_MERGE_DRIFT_NS`` (its
    values interpolated between the base's, as the driver's linear interpolation gives them)."""
    k = np.arange(RS_MERGE_EVERY - 1, len(base_ns) - 1, RS_MERGE_EVERY)
    step = base_ns[k + 1] - base_ns[k]
    phase = ((base_ns[k] - base_ns[0]) // RS_MERGE_EVERY * RS_MERGE_DRIFT_NS // RS_IMU_PERIOD_NS) % step
    extra = base_ns[k] + np.clip(phase, 700, step - 700)  # never on a base stamp (700 ns: the recording's shortest)
    u = ((extra - base_ns[k]) / step)[:, None]
    stamps = np.concatenate([base_ns, extra])
    order = np.argsort(stamps, kind="stable")
    g = np.concatenate([gyro, (1 - u) * gyro[k] + u * gyro[k + 1]])
    a = np.concatenate([accel, (1 - u) * accel[k] + u * accel[k + 1]])
    return stamps[order], g[order], a[order]


def frame_grid(imu_ns: np.ndarray, lo: int, hi: int, period_ns: int) -> np.ndarray:
    """Camera stamps [n] int64 ns in [lo, hi] on the IMU's own stamps ``imu_ns`` (sorted int64 ns), as EuRoC triggers
    cam0 on the IMU clock: the IMU stamp nearest to each ``t0 + k period_ns``, t0 the first IMU stamp at or after
    ``lo`` (integer ns throughout: float64 at EuRoC epochs resolves only ~0.24 us)."""
    inside = imu_ns[(imu_ns >= lo) & (imu_ns <= hi)]
    if len(inside) < 2:
        return inside
    want = inside[0] + np.arange((inside[-1] - inside[0]) // period_ns + 1, dtype=np.int64) * period_ns
    after = np.clip(np.searchsorted(inside, want), 1, len(inside) - 1)
    nearer_before = want - inside[after - 1] <= inside[after] - want
    return np.unique(np.where(nearer_before, inside[after - 1], inside[after]))


def gt_brackets(gt_ns: np.ndarray, ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For stamps ``ns`` [n] int64 within the sorted GT stamps ``gt_ns`` [k] int64 (both ns): the indices [n] of the
    last GT row at or before and of the first GT row at or after each stamp (the same row for a stamp on a row)."""
    return np.searchsorted(gt_ns, ns, side="right") - 1, np.searchsorted(gt_ns, ns, side="left")


def euroc_frames(imu_ns: np.ndarray, gt_ns: np.ndarray, period_ns: int, *, start_ns: int = 0,
                 length_ns: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Where to render cam0 along a recording with IMU stamps ``imu_ns`` and GT stamps ``gt_ns`` (sorted, int64 ns):
    ``frame_grid`` over the span both cover, from ``start_ns`` into it, for ``length_ns`` (None: to its end), leaving
    out the frames in a GT gap (bracketing GT rows more than ``MAX_GT_GAP_NS`` apart). Returns (the frames' stamps
    [n] int64 ns, the gaps frames were left out of [G,2] int64 ns: the GT rows either side of each). Raises
    DataError when fewer than two frames remain."""
    lo, hi = max(int(imu_ns[0]), int(gt_ns[0])), min(int(imu_ns[-1]), int(gt_ns[-1]))
    if hi - lo < period_ns:
        raise DataError(f"the IMU [{imu_ns[0]}, {imu_ns[-1]}] ns and the ground truth [{gt_ns[0]}, {gt_ns[-1]}] ns "
                        "share less than one camera period")
    candidates = frame_grid(imu_ns, lo, hi, period_ns)
    candidates = candidates[candidates >= lo + start_ns]
    before, after = gt_brackets(gt_ns, candidates)
    measured = gt_ns[after] - gt_ns[before] <= MAX_GT_GAP_NS
    frames = candidates[measured]
    if length_ns is not None and len(frames):
        frames = frames[frames <= frames[0] + length_ns]
    skipped = ~measured & (candidates <= (frames[-1] if len(frames) else hi))
    gaps = np.unique(np.stack([gt_ns[before[skipped]], gt_ns[after[skipped]]], 1), axis=0)
    if len(frames) < 2:
        raise DataError(f"fewer than two camera frames fit in the span covered by both IMU and GT "
                        f"({(hi - lo) * 1e-9:.2f} s) after start {start_ns * 1e-9:g} s"
                        + (f" outside its {len(gaps)} GT gaps > {MAX_GT_GAP_NS * 1e-9:g} s" if len(gaps) else ""))
    return frames, gaps


class _Euroc(_Source):
    """A real EuRoC recording to render along (see the module docstring)."""

    def __init__(self, spec: SequenceSpec) -> None:
        self.src = src = euroc_mav0(spec.from_euroc)
        imu_ns, imu = asl.read_imu(src)
        gt = asl.read_groundtruth(src)
        if gt is None:
            raise DataError(f"{src}: no state_groundtruth_estimate0/ to follow (rendering needs the GT trajectory)")
        self.calib = load_calib(src / "cam0" / "sensor.yaml")
        if len(imu_ns) < 2 or np.any(np.diff(imu_ns) <= 0):
            raise DataError(f"{src / 'imu0' / 'data.csv'}: needs >= 2 strictly increasing stamps")
        try:
            cam_ns, self.gt_gaps = euroc_frames(
                imu_ns, gt.t_ns, int(round(1e9 / (self.calib.rate_hz or euroc.CAMERA_RATE_HZ))),
                start_ns=int(round(spec.start_s * 1e9)),
                length_ns=None if spec.seconds is None else int(round(spec.seconds * 1e9)))
        except DataError as err:
            raise DataError(f"{src}: {err}") from None
        # All IMU samples up to the frames (a later start keeps IMU_HISTORY_NS before the first), then a margin.
        first = imu_ns[0] if not spec.start_s else cam_ns[0] - IMU_HISTORY_NS
        imu_keep = (imu_ns >= first) & (imu_ns <= cam_ns[-1] + IMU_MARGIN_NS)
        imu_ns, imu = imu_ns[imu_keep], imu.select(imu_keep)
        # The GT rows over that IMU span and the rows bracketing the first and last frames (GT may start before the
        # IMU or end after it): the written track covers every frame.
        before, after = gt_brackets(gt.t_ns, cam_ns[[0, -1]])
        gt_keep = (gt.t_ns >= min(imu_ns[0], gt.t_ns[before[0]])) & (gt.t_ns <= max(imu_ns[-1], gt.t_ns[after[1]]))
        self.imu_ns, self.imu = imu_ns, imu
        self.gt_ns, self.T_WB, self.v_WB = gt.t_ns[gt_keep], gt.T_WB[gt_keep], gt.v_WB[gt_keep]
        self.bg, self.ba = gt.bg[gt_keep], gt.ba[gt_keep]
        t = (gt.t_ns - gt.t_ns[0]) * 1e-9
        position = CubicHermiteSpline(t, gt.T_WB[:, :3, 3], gt.v_WB, axis=0)
        attitude = RotationSpline(t, Rotation.from_matrix(gt.T_WB[:, :3, :3]))
        tc = (cam_ns - gt.t_ns[0]) * 1e-9
        self.cam_ns = cam_ns
        self.T_WC = so3.make_T(attitude(tc).as_matrix(), position(tc)) @ self.calib.T_BC
        self.first_ns, self.last_ns = int(min(imu_ns[0], self.gt_ns[0])), int(max(imu_ns[-1], self.gt_ns[-1]))
        body = position(tc)
        self.center = 0.5 * (body.min(0) + body.max(0))
        self.extent = 0.5 * (body.max(0) - body.min(0)) + 0.1  # 10 cm beyond the flown box

    def block(self, ns0: int, ns1: int) -> Block:
        c, i, g = _in(self.cam_ns, ns0, ns1), _in(self.imu_ns, ns0, ns1), _in(self.gt_ns, ns0, ns1)
        return Block(self.cam_ns[c], self.T_WC[c], self.imu_ns[i], self.imu.select(i), self.gt_ns[g],
                     self.T_WB[g], self.v_WB[g], self.bg[g], self.ba[g])


def write_sequence(mav0, spec: SequenceSpec, *, workers: int = 2,
                   on_block: Callable[[Block], None] | None = None) -> Written:
    """Write the sequence ``spec`` into the (new or empty) folder ``mav0``, a block at a time; ``on_block`` gets
    each block's streams in time order (e.g. to write a bag in the same pass). ``workers`` threads render and encode
    frames (numpy and OpenCV release the GIL). Returns the calibration the frames were rendered with and the GT
    gaps left without frames."""
    mav0 = Path(mav0)
    if spec.from_euroc is None:
        world = make_scene(spec.scene, spec.seed)
        source: _Generated | _Euroc = _Generated(spec, world)
    else:
        source = _Euroc(spec)
        world = make_scene(spec.scene, spec.seed, center=source.center, extent=source.extent)
    writer = asl.AslWriter(mav0, with_depth=spec.with_depth)
    if spec.from_euroc is None:
        asl.write_sensor_yaml(mav0, source.calib, source.noise)
    else:  # the recording's own calibration files, unchanged
        for rel in ("cam0/sensor.yaml", "imu0/sensor.yaml", "state_groundtruth_estimate0/sensor.yaml", "body.yaml"):
            if (source.src / rel).is_file():
                shutil.copyfile(source.src / rel, mav0 / rel)
    if spec.with_depth:
        asl.write_depth_yaml(mav0, source.calib.undistorter().K)
    source.renderer = Renderer(world, source.calib)

    def render(ns: int, T_WC: np.ndarray, exposure: np.ndarray | None) -> np.ndarray:
        image, depth = source.render(ns, T_WC, exposure, spec.with_depth)
        asl.write_image(writer.image_dir, ns, image)
        if writer.depth_dir is not None:
            asl.write_depth(writer.depth_dir, ns, depth)
        return image

    def finish(rows: Block, frames: list) -> None:
        images = tuple(f.result() for f in frames)
        writer.frames(rows.cam_ns)
        writer.imu(rows.imu_ns, rows.imu)
        writer.groundtruth(rows.gt_ns, rows.T_WB, rows.v_WB, rows.bg, rows.ba)
        if on_block is not None:
            on_block(replace(rows, images=images))

    pool = ThreadPoolExecutor(max(workers, 1))
    try:
        pending = None  # the block being rendered while the next one is submitted
        for ns0 in range(source.first_ns, source.last_ns + 1, BLOCK_NS):
            rows = source.block(ns0, ns0 + BLOCK_NS)
            exposure = rows.exposure if rows.exposure is not None else [None] * len(rows.cam_ns)
            frames = [pool.submit(render, ns, T, e) for ns, T, e in zip(rows.cam_ns.tolist(), rows.T_WC, exposure)]
            if pending is not None:
                finish(*pending)
            pending = (rows, frames)
        if pending is not None:
            finish(*pending)
    finally:  # an error or an interrupt: drop queued frames, wait for those being written
        pool.shutdown(wait=True, cancel_futures=True)
    return Written(source.calib, source.gt_gaps)


# ------------------------------------------------------------------------------------------- staging and cache
def staging_dir(parent) -> Path:
    """A new hidden folder ``parent/.vi3-generating.<pid>.<random>`` to write into before renaming."""
    parent = Path(parent)
    parent.mkdir(parents=True, exist_ok=True)
    remove_stale_staging(parent)
    return Path(tempfile.mkdtemp(prefix=f"{STAGING_PREFIX}{os.getpid()}.", dir=parent))


def remove_stale_staging(parent) -> list[Path]:
    """Remove the staging folders in ``parent`` that runs which are gone left behind (killed, crashed): those whose
    pid is no running process, and those of earlier versions without a pid that are over an hour old. Returns them."""
    removed = []
    for path in Path(parent).glob(f"{STAGING_PREFIX}*"):
        pid = path.name[len(STAGING_PREFIX):].split(".")[0]
        if pid.isdigit():
            stale = not _alive(int(pid))
        else:
            stale = time.time() - path.stat().st_mtime > 3600.0
        if stale and path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def generate_sequence(out_dir, *, workers: int = 2, **spec) -> Path:
    """Write the ASL sequence ``SequenceSpec(**spec)`` to ``out_dir/mav0`` and return ``out_dir`` (cached).

    If ``out_dir`` already holds a complete sequence generated with the same spec and ``GENERATOR_VERSION`` it is
    reused. The sequence is written to a staging folder inside ``out_dir`` first and renamed, so concurrent callers
    are safe.
    """
    out_dir = Path(out_dir)
    params = {**asdict(SequenceSpec(**spec)), "version": GENERATOR_VERSION}
    params["seconds"] = None if params["seconds"] is None else float(params["seconds"])
    marker = out_dir / "mav0" / "vi3_generated.json"
    if _matches(marker, params):
        return out_dir
    tmp = staging_dir(out_dir)
    try:
        write_sequence(tmp / "mav0", SequenceSpec(**spec), workers=workers)
        (tmp / "mav0" / "vi3_generated.json").write_text(json.dumps(params))
        if _matches(marker, params):  # another process finished the same sequence meanwhile
            return out_dir
        shutil.rmtree(out_dir / "mav0", ignore_errors=True)  # a sequence made with other parameters
        try:
            os.rename(tmp / "mav0", out_dir / "mav0")
        except OSError:
            if not _matches(marker, params):
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out_dir


def generation_tag(out_dir) -> str:
    """A short digest of the parameters and generator version ``out_dir`` was generated with: files derived from the
    sequence (bags converted from it) are cached under it, so a regenerated sequence never meets stale ones."""
    marker = Path(out_dir) / "mav0" / "vi3_generated.json"
    return hashlib.sha1(marker.read_bytes()).hexdigest()[:10]


def _matches(marker: Path, params: dict) -> bool:
    try:
        return json.loads(marker.read_text()) == params
    except (OSError, ValueError):
        return False


def cached_sequence(cache_dir, *, seconds: float | None = 4.0, seed: int = 0, scene: str = "room",
                    motion: str = "medium", accel_bias: bool = True, imu_noise: bool = True, with_depth: bool = True,
                    from_euroc=None, start_s: float = 0.0) -> Path:
    """``generate_sequence`` into ``cache_dir/<key>`` where the key names every parameter that is not the default
    (``room_seed0_4s`` is the default medium-motion sequence with accelerometer bias, noise and depth)."""
    length = "all" if seconds is None else f"{seconds:g}s"
    key = f"{scene}_seed{seed}_{length}" + ("" if motion == "medium" else f"_{motion}") \
        + ("" if accel_bias else "_noaccelbias") + ("" if imu_noise else "_noisefree") \
        + ("" if with_depth else "_nodepth")
    if from_euroc is not None:
        key = f"euroc_{euroc_mav0(from_euroc).resolve().parent.name}_from{start_s:g}s_{key}"
    return generate_sequence(Path(cache_dir) / key, seconds=seconds, seed=seed, scene=scene, motion=motion,
                             accel_bias=accel_bias, imu_noise=imu_noise, with_depth=with_depth,
                             from_euroc=None if from_euroc is None else str(from_euroc), start_s=start_s)


def bench_cache_dir() -> Path:
    """Where benchmarks keep generated sequences (``VI3_CACHE``, default ``.cache/bench`` in the working dir)."""
    return Path(os.environ.get("VI3_CACHE", ".cache")) / "bench"


def bench_clip() -> Clip:
    """The benchmarks' clip: the middle paper clip (8 frames at stride 2, 752x480) of a generated 3 s sequence,
    cached in ``bench_cache_dir``, without depth."""
    seq = asl.read_asl(cached_sequence(bench_cache_dir(), seconds=3.0, seed=0) / "mav0")
    return make_clip(seq, sample_clips(len(seq), mode="paper")[1], with_depth=False)
