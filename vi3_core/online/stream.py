"""``StreamEstimator``: the one per-clip loop of a camera + IMU stream, shared by the node, replay and ``vi3 eval``.

Per clip: with ``shared_frames``, the last frames of the clip before it in the window in place of its first ones when
clips in between were dropped (``_compose``); the rig's self-calibration where its sigma allows
(``RigEstimate.apply``: the camera mount turned, the IMU moved onto the frames' clock by the time offset); a rolling
shutter's frames turned back to their stamps by the gyro (``_derolled``); the
initialisation's data checks (a clip they reject costs no inference); the backbone and the anchoring mode
(``vi3_core.anchor.anchor``) with the stream's initialisation; then the clip's place in the odom trajectory, and its
rotations (as configured) added to the rig's estimate.
The initialisation is the online window's (``OnlineEstimator``: gravity, biases and velocity carried across clips,
the clips chained into odom) with ``online``; every clip on its own as in the paper without it; or, for evaluation,
the oracle from the clip's ground truth. ``process`` returns everything the clip changed as a ``ClipOutcome``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum

import cv2
import numpy as np

from vi3_core.anchor import MODES, AnchorOptions, anchor, check_mode
from vi3_core.backbones.base import Backbone, GyroRotations
from vi3_core.init import InitOptions, oracle_init, validate
from vi3_core.online.calibration import CalibrationOptions, RigCalibrator, RigEstimate, frame_rates
from vi3_core.online.chain import ChainedClip, OdomState, Trajectory
from vi3_core.online.estimator import OnlineDecision, OnlineEstimator
from vi3_core.online.options import OnlineOptions
from vi3_core.rolling_shutter import derolled
from vi3_core.types import AnchorResult, Clip, InitResult, InitStatus

IMU_LEAD_MARGIN_S = 0.005  # s: the most a clip waits for IMU beyond the estimated time offset (``imu_lead``)
MAX_READOUT_S = 0.1  # s: a rolling shutter's readout beyond this is no camera's (a frame interval at 10 Hz)
INIT_SOURCES = ("vi3", "gt")


@dataclass(frozen=True)
class StreamOptions:
    """online: carry the metric state across clips (the online window and the odom chaining); false: every clip on
    its own (the paper). mode: the anchoring mode (init | cond | ttr). init_source: "vi3", the GT-free
    initialisation, or "gt", the oracle from the clip's ground truth (evaluation only: every clip on its own).
    all_depth: every frame's depth is read downstream (the node publishes every frame's depth or points); else only
    the frames the stream itself reads get depth from a backbone that predicts depth frame by frame
    (``StreamEstimator.depth_frames``). rolling_shutter_readout: s from the first row's exposure to the last's of a
    rolling-shutter camera, whose frames are then turned back to their stamps' camera by the gyro before the backbone
    sees them (``vi3_core.rolling_shutter``); 0: a global shutter. gyro_prior: hand the backbone each clip's
    rotations from the gyro once the window has a gyro-bias estimate (``GyroRotations``; the ``classical`` backbone's
    bundle adjustment takes them as a prior); false: the backbone sees the images alone."""

    online: bool = True
    mode: str = "init"
    init_source: str = "vi3"
    all_depth: bool = False
    rolling_shutter_readout: float = 0.0
    gyro_prior: bool = True

    def __post_init__(self) -> None:
        if not 0.0 <= self.rolling_shutter_readout <= MAX_READOUT_S:
            raise ValueError(f"rolling_shutter_readout must be in [0, {MAX_READOUT_S}] s; got "
                             f"{self.rolling_shutter_readout!r}")
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}; got {self.mode!r}")
        if self.init_source not in INIT_SOURCES:
            raise ValueError(f"init_source must be one of {', '.join(INIT_SOURCES)}; got {self.init_source!r}")
        if self.online and self.init_source != "vi3":
            raise ValueError("the online window is GT-free: init_source 'gt' needs online false")


class InOdom(StrEnum):
    """How a clip went into odom (``ClipOutcome.in_odom``): placed with its claim, placed at the window's scale without
    one, or not placed."""

    CLAIMED = "claimed"
    WINDOW_SCALE = "window scale, not claimed"  # ``OdomChain.places_unclaimed``: odometry only
    NOT_PLACED = "not placed"


@dataclass
class ClipOutcome:
    """What one clip changed.

    clip: the clip as processed (with the shared frames in place of its first ones where ``_compose`` put them, the
    applied parts of the rig's estimate: its mount turned, its IMU moved by the time offset; its stamps as
    configured; a rolling shutter's frames turned back to their stamps);
    init: the clip's initialisation (the window's with ``online``), also when the backbone did not run; result: the
    final ``AnchorResult`` (None when the data checks rejected the clip before the backbone); fast: the init-mode
    result that ``cond``/``ttr`` refine (None in ``init`` mode or when the init is not ok); decision: the online
    window's decision, with the clip's own initialisation (None without ``online``); chained: the clip placed in odom
    (None unless it was chained); state: the odom state after the clip, where IMU-rate propagation starts (None
    before the first chained clip; its stamps on the IMU's clock); segment: the odom segment the trajectory is in (0:
    the first); calibration: the rig's estimate after the clip (None without self-calibration); calibration_note: why
    the clip did not add to it ("" when it did)."""

    clip: Clip
    init: InitResult
    result: AnchorResult | None = None
    fast: AnchorResult | None = None
    decision: OnlineDecision | None = None
    chained: ChainedClip | None = None
    state: OdomState | None = None
    segment: int = 0
    calibration: RigEstimate | None = None
    calibration_note: str = ""

    @property
    def mode(self) -> str:
        """The anchoring mode that ran ("none" when the init is not ok or the backbone did not run)."""
        return self.result.mode if self.result is not None else "none"

    @property
    def in_odom(self) -> InOdom:
        """How the clip went into odom: its claim, the window's scale without a claim, or not at all."""
        if self.chained is None:
            return InOdom.NOT_PLACED
        return InOdom.CLAIMED if self.init.ok else InOdom.WINDOW_SCALE


class StreamEstimator:
    """The clips of one stream, in time order, through the backbone, the initialisation and the odom chaining.

    ``process(clip)`` -> ``ClipOutcome``; ``trajectory`` is the chained odom trajectory so far. Deterministic: the
    same clips give the same outcomes. Not thread-safe: one caller (the node's worker thread) processes the clips."""

    def __init__(self, backbone: Backbone, *, options: StreamOptions | None = None,
                 online: OnlineOptions | None = None, init: InitOptions | None = None,
                 anchor: AnchorOptions | None = None, calibration: CalibrationOptions | None = None) -> None:
        self.options = options or StreamOptions()
        check_mode(backbone, self.options.mode)  # an unsupported mode fails here, not once per clip
        self.backbone = backbone
        backbone.forget()  # a new stream: nothing of another stream's frames carries into it
        self.online_options = online or OnlineOptions()
        self.init_options = init or InitOptions()
        self.accel_A = self.init_options.accel_A  # the accelerometer's calibration (None: none), parsed once
        self.anchor_options = anchor or AnchorOptions()
        self.window = OnlineEstimator(options=self.online_options, init_options=self.init_options) \
            if self.options.online else None
        calibration = calibration or CalibrationOptions()
        self.calibrator = RigCalibrator(calibration, max_rotation_error_deg=self.init_options.max_rotation_error) \
            if self.options.online and calibration.self_calibration else None
        self._chained_offset = 0.0  # s: the time offset applied to the last chained clip (``_state``)
        # the last frames derolled (stamps [k] s, frames, ground-truth depth or None), for a clip that starts with them
        self._turned: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None = None

    @property
    def imu_lead(self) -> float:
        """s of IMU the next clip should carry in its history beyond its last frame (``make_clip``'s ``lead_s``, the
        node's ``ClipBuffer.imu_lead``): the rig's estimated time offset where it is positive (a frame then shows the
        body at a later IMU time), plus three of its sigmas up to ``IMU_LEAD_MARGIN_S``, so that the estimate can be
        applied to a clip that was cut while an earlier one was still being processed (and the estimate moved); 0
        without self-calibration."""
        if self.calibrator is None:
            return 0.0
        est = self.calibrator.estimate
        return max(0.0, est.time_offset + min(3.0 * est.time_offset_sigma, IMU_LEAD_MARGIN_S))

    def _clock_sigma(self, current: RigEstimate | None, rig: RigEstimate | None) -> float:
        """s: how far the clip's IMU may be off its frames' clock: the applied time offset's sigma; else, with
        self-calibration, how far the rig's estimate puts the configured offset (its sigma included); else the error
        model's ``time_offset_sigma``."""
        if rig is not None and rig.offset_applied:
            return rig.time_offset_sigma
        if current is not None:
            return math.hypot(current.time_offset, current.time_offset_sigma)
        return self.init_options.time_offset_sigma

    def reset(self, reason: str) -> None:
        """Forget the stream (``reason``: time went back, so the window, its biases, the kept IMU, the odom state and
        what the backbone kept of earlier clips no longer hold): the next clip starts as the first did, except that the
        trajectory's segments count on and the next chained clip starts a new one (``OnlineEstimator.continue_after``).
        The rig's self-calibration is kept (the rig did not change), its random walk restarting from the next clip.
        Without ``online`` only the backbone has anything to forget."""
        self.backbone.forget()
        if self.window is not None:
            previous = self.window.trajectory
            self.window = OnlineEstimator(options=self.online_options, init_options=self.init_options)
            self.window.continue_after(previous, reason)
            self._chained_offset = 0.0
        self._turned = None
        if self.calibrator is not None:
            self.calibrator.t_last = None

    @property
    def trajectory(self) -> Trajectory:
        """The chained odom trajectory (empty without ``online``)."""
        return self.window.trajectory if self.window is not None else Trajectory()

    @property
    def decision(self) -> OnlineDecision | None:
        """The online window's decision on the latest clip it initialised (None without ``online``)."""
        return self.window.last if self.window is not None else None

    def process(self, clip: Clip, *, on_init: Callable[[Clip, AnchorResult], None] | None = None,
                before_backbone: Callable[[], bool] | None = None) -> ClipOutcome | None:
        """One clip (undistorted, with the IMU covering it and, with ``online``, the IMU history back to
        ``online_max_bridge``). ``on_init(clip, result)`` receives the clip as processed and its fast init-mode
        result when it is ok, before ``cond``/``ttr`` refine it (the node publishes it at once). ``before_backbone``
        is called once the clip passed the data checks; when it returns False the clip is abandoned (None: nothing
        changed). Bad data never raises: it is the outcome's ``init`` status."""
        A = self.accel_A
        if A is not None:
            history = None if clip.imu_history is None else clip.imu_history.read_through(A)
            clip = dataclasses.replace(clip, imu=clip.imu.read_through(A), imu_history=history)
        configured, shared = self._compose(clip)
        current = self.calibrator.estimate if self.calibrator is not None else None
        rig = current.for_clip(configured) if current is not None else None
        clip = rig.apply(configured) if rig is not None else configured
        short = ("time offset not applied: the clip's IMU ends before its frames' moved times"
                 if rig is not None and current.offset_applied and not rig.offset_applied else "")
        reason = validate.check_stamps(clip.stamps) or validate.check_imu(clip.imu, clip.stamps, self.init_options)
        if reason is not None:
            init = InitResult(InitStatus.REJECTED, reason)
            decision = OnlineDecision(rejected={"clip": reason}, own=init) if self.window is not None else None
            return ClipOutcome(clip, init, decision=decision, state=self._state(), segment=self._segment(),
                               calibration=rig)
        if before_backbone is not None and not before_backbone():
            return None
        clip = self._derolled(clip, shared)
        # without the window each clip stands alone (the independent evaluation runs its clips in any order); with
        # it, the gyro's rotations on the clock and through the mount the rig applied, at the window's gyro bias
        bias = self.window.gyro_bias if self.window is not None and self.options.gyro_prior else None
        gyro = GyroRotations.of(clip, *bias, self._clock_sigma(current, rig)) if bias is not None else None
        self.backbone.bind(configured, depth_frames=self.depth_frames(configured.n), continued=self.window is not None,
                           gyro=gyro)
        fast: list[AnchorResult] = []

        def take_fast(result: AnchorResult) -> None:
            if self.options.mode != "init" and result.init.ok:
                fast.append(result)
                if on_init is not None:
                    on_init(clip, result)

        result = anchor(clip, self.backbone, mode=self.options.mode, options=self.anchor_options,
                        init_options=self.init_options, init=self._initialiser(clip), on_init=take_fast)
        window = self.window
        chained = window.update(clip, result) if window is not None else None
        note = ""
        if chained is not None:
            self._chained_offset = rig.time_offset if rig is not None and rig.offset_applied else 0.0
        if self.calibrator is not None:  # the rotations as configured, whatever became of the clip
            bg = result.init.bg if np.all(np.isfinite(result.init.bg)) else np.zeros(3)
            note = "; ".join(filter(None, [short, self.calibrator.add(configured, result.base, bg)]))
            rig = self.calibrator.estimate
        return ClipOutcome(clip, result.init, result, fast[0] if fast else None,
                           window.last if window is not None else None, chained, self._state(), self._segment(),
                           rig, note)

    def depth_frames(self, n: int) -> np.ndarray | None:
        """The frames of an n-frame clip whose depth is read (None: every frame): in ``init`` mode the last (what the
        node publishes, ``depth_frames`` / ``points_frames`` last) and, online, the first and last ``shared_frames``
        (the scale links to the clips before and after); every frame with ``all_depth`` or in cond / ttr mode (the
        refinement's losses use every frame's depth)."""
        if self.options.all_depth or self.options.mode != "init":
            return None
        k = self._shared_frames
        return np.unique(np.concatenate([np.arange(min(k, n)), np.arange(max(n - max(k, 1), 0), n)]))

    @property
    def _shared_frames(self) -> int:
        """Frames a clip starts with from the clip before it (``OnlineOptions.shared_frames``; 0 without the window,
        where every clip stands alone)."""
        return self.online_options.shared_frames if self.window is not None else 0

    def _compose(self, clip: Clip) -> tuple[Clip, int]:
        """``clip``, or with the window's shared frames in place of its first ones when it does not start with them
        (the clips in between were dropped) and they end at most ``shared_max_gap`` before its own frames: so that
        its scale is linked to the window's through frames both clips predicted; and how many frames were put in."""
        shared = self.window.shared if self.window is not None else None
        if shared is None or shared.starts(clip) or clip.n <= len(shared):
            return clip, 0
        gap = float(clip.stamps[len(shared)] - shared.stamps[-1])
        if not 0.0 < gap <= self.online_options.shared_max_gap:  # never with the default 0
            return clip, 0
        composed = shared.into(clip)
        return (composed, len(shared)) if composed is not None else (clip, 0)

    def _derolled(self, clip: Clip, skip: int) -> Clip:
        """``clip`` with its frames from ``skip`` on turned back to their stamps' camera (``rolling_shutter_readout``;
        the frames before were, as frames of the clip they came from), and its ground-truth depth with them where it
        has any (evaluation): the camera's rate during each frame is the gyro's mean over its readout from the clip's
        IMU, on the frames' clock, through the camera mount (the gyro bias, a fraction of a pixel over a readout,
        left). A frame is turned once: a clip that starts with the frames the clip before it ended with takes them
        as they were turned there (with the rate around a clip's last frame, from its IMU that ends one sample after
        it), so that the frames two clips share, and their scale link, are the same in both."""
        readout = self.options.rolling_shutter_readout
        if not readout or skip >= clip.n:
            return clip
        images = clip.images.copy()
        gt = clip.gt
        depth = None if gt is None or gt.depth is None or gt.depth.shape[1:3] != images.shape[1:3] else \
            np.array(gt.depth, np.float32, copy=True)
        turned = self._turned
        if turned is not None and skip == 0:
            stamps, frames, frames_depth = turned
            k = len(stamps)
            if k < clip.n and np.array_equal(clip.stamps[:k], stamps) and frames.shape[1:] == images.shape[1:]:
                images[:k] = frames
                if depth is not None and frames_depth is not None:
                    depth[:k] = frames_depth
                skip = k
        rates = frame_rates(clip.imu, clip.stamps[skip:], 0.5 * readout) @ clip.T_BC[:3, :3]
        images[skip:] = derolled(clip.images[skip:], clip.K, rates, readout)
        if depth is not None:
            depth[skip:] = derolled(depth[skip:], clip.K, rates, readout, interpolation=cv2.INTER_NEAREST)
            gt = dataclasses.replace(gt, depth=depth)
        k = self._shared_frames
        self._turned = None if not 0 < k < clip.n else \
            (np.array(clip.stamps[-k:]), images[-k:].copy(), None if depth is None else depth[-k:].copy())
        return dataclasses.replace(clip, images=images, gt=gt)

    def _initialiser(self, clip: Clip) -> Callable | None:
        """The initialisation ``anchor`` runs on the base geometry (None: its own per-clip GT-free one)."""
        if self.options.init_source == "gt":
            return lambda base: oracle_init(clip, base, options=self.init_options)
        if self.window is not None:
            return lambda base: self.window.initialise(clip, base)
        return None

    def _state(self) -> OdomState | None:
        """The window's state of the last chained clip with its stamps on the IMU's clock (moved by the time offset
        applied to that clip), where propagation through the raw IMU starts."""
        state = self.window.state if self.window is not None else None
        if state is None or not self._chained_offset:
            return state
        return dataclasses.replace(state, stamps=state.stamps + self._chained_offset)

    def _segment(self) -> int:
        return len(self.trajectory.resets)


__all__ = ["INIT_SOURCES", "MAX_READOUT_S", "ClipOutcome", "InOdom", "StreamEstimator", "StreamOptions"]
