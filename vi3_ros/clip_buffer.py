"""Clip buffering: turn a live stream of camera frames and IMU samples into clips of n frames.

Pure Python/numpy, no ROS: the node feeds it from its subscriptions and the replay tool from a bag, so both
produce exactly the same clips.

Time base. Every stamp inside the buffer is in IMU time. Camera stamps are shifted at the edge,
``t_imu = t_cam + time_offset`` (Kalibr's ``timeshift_cam_imu`` convention), so ``add_image`` takes the
message stamp and the clip's ``stamps`` are already corrected (``Clip.stamps`` is documented that way).

Frame selection. Input frames are numbered from the last (re)start. A clip starts every ``hop`` frames (default
``n * stride``: non-overlapping) and takes every ``stride``-th frame from its start until it has ``n`` frames.
A clip is emitted once the IMU reaches ``imu_margin`` samples past its last frame (interpolation and
preintegration need a sample on each side). Faults become ``Drop`` events with a named ``reason``:

- ``image_out_of_order`` / ``image_duplicate`` / ``imu_out_of_order`` / ``imu_duplicate``: the message is dropped;
- ``frame_gap``: two consecutive frames further apart than ``max_frame_gap``; open clips are dropped and
  collection restarts at the new frame;
- ``imu_missing``: the IMU buffer does not reach back to the clip's first frame, i.e. has no sample at or before
  it (IMU started late, or the bounded buffer overflowed); the clip's IMU is ``vi3_core.types.window_bounds``'s
  window, as in the evaluation;
- ``imu_stalled``: no IMU past the clip's last frame ``imu_timeout`` seconds (camera time) after it;
- ``frame_overflow``: more clips waiting for IMU than ``max_pending`` (the oldest is dropped).

Cost. An IMU sample is O(1) amortised: samples go into preallocated arrays, and arrays are cut out only when a clip
is emitted. Stamps are int ns at the inputs and in ``Drop.stamp_ns`` (exact), float64 s (IMU time) inside.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass, field

import numpy as np

from vi3_core.errors import DataError
from vi3_core.types import CLIP_LENGTH, CLIP_STRIDE, ImuSamples, window_bounds


@dataclass(frozen=True)
class ClipBufferOptions:
    """clip_length: frames per clip (n); stride: take every stride-th input frame; hop: input frames between clip
    starts (None: clip_length * stride, non-overlapping); max_frame_gap: s, larger gap between consecutive input frames
    restarts collection (<= 0: automatic, 1.5 x the median of the recent frame intervals); time_offset: s, t_imu =
    t_cam + time_offset; imu_margin: IMU samples needed beyond the last frame; imu_buffer: bounded IMU buffer
    (samples); imu_timeout: s of camera time a complete clip waits for IMU before it is dropped; imu_history: s of IMU
    kept before the clip's first frame in ``RawClip.imu_history`` (long-window gravity seed; 0 = none), which also
    reaches ``ClipBuffer.imu_lead`` s beyond its last frame; max_pending: complete clips waiting for IMU."""

    clip_length: int = CLIP_LENGTH
    stride: int = CLIP_STRIDE
    hop: int | None = None
    max_frame_gap: float = 0.0
    time_offset: float = 0.0
    imu_margin: int = 1
    imu_buffer: int = 4000
    imu_timeout: float = 0.5
    imu_history: float = 0.0
    max_pending: int = 4

    def __post_init__(self) -> None:
        checks = {"clip_length >= 2": self.clip_length >= 2, "stride >= 1": self.stride >= 1,
                  "hop >= 1": self.hop is None or self.hop >= 1, "imu_margin >= 1": self.imu_margin >= 1,
                  "imu_buffer >= 16": self.imu_buffer >= 16, "imu_timeout > 0": self.imu_timeout > 0,
                  "imu_history >= 0": self.imu_history >= 0, "max_pending >= 1": self.max_pending >= 1}
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise DataError(f"ClipBufferOptions: {', '.join(bad)} violated by {self}")

    @property
    def clip_hop(self) -> int:
        return self.hop if self.hop is not None else self.clip_length * self.stride


@dataclass(frozen=True)
class RawClip:
    """n frames as recorded plus the IMU covering them.

    index: running clip number (0, 1, ...); stamps: [n] float64 s in IMU time; stamps_ns: [n] the frames' original
    message stamps (camera time, int ns, for the output headers); images: the n raw (distorted) frames as given;
    imu: samples covering [stamps[0], stamps[-1]] plus ``imu_margin`` samples each side; imu_history: samples from
    the last one at or before ``ClipBufferOptions.imu_history`` s before stamps[0] to the end of ``imu`` (None when that
    is 0).
    """

    index: int
    stamps: np.ndarray
    stamps_ns: np.ndarray
    images: tuple[np.ndarray, ...]
    imu: ImuSamples
    imu_history: ImuSamples | None = None


@dataclass(frozen=True)
class Drop:
    """A message or clip that was discarded: ``reason`` is one of the names in the module docstring; the stamp
    concerned as ``t`` (float64 s, IMU time) and ``stamp_ns`` (the message's own header stamp, int ns, exact: camera
    time for frames and clips, IMU time for IMU samples); ``detail`` a human-readable sentence; ``clip`` the clip
    index or -1."""

    reason: str
    t: float
    stamp_ns: int
    detail: str
    clip: int = -1


@dataclass
class _Open:
    start: int  # input frame number of the first frame
    stamps: list[float] = field(default_factory=list)
    stamps_ns: list[int] = field(default_factory=list)
    images: list[np.ndarray] = field(default_factory=list)


_ROW = 10  # gyro [3] rad/s, accel [3] m/s^2, orientation [4] xyzw (NaN: none)


class _ImuRing:
    """The newest ``capacity`` IMU samples in preallocated arrays of twice that length: ``append`` is O(1)
    amortised (when the storage end is reached, the kept samples move to the front once per ``capacity`` appends)
    and ``t`` / ``rows`` are contiguous views [len] float64 s and [len,10] (``_ROW``), oldest first."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._t = np.empty(2 * capacity)
        self._rows = np.empty((2 * capacity, _ROW))
        self._start = self._end = 0

    def __len__(self) -> int:
        return self._end - self._start

    def append(self, t: float, gyro, accel, orientation) -> None:
        """One sample: t s, gyro [3] rad/s, accel [3] m/s^2, orientation [4] xyzw (NaN: none)."""
        if self._end == len(self._t):
            n = len(self)
            self._t[:n], self._rows[:n] = self._t[self._start:self._end], self._rows[self._start:self._end]
            self._start, self._end = 0, n
        self._t[self._end] = t
        row = self._rows[self._end]
        row[0:3], row[3:6], row[6:10] = gyro, accel, orientation
        self._end += 1
        if len(self) > self.capacity:
            self._start += 1

    @property
    def t(self) -> np.ndarray:
        return self._t[self._start:self._end]

    @property
    def rows(self) -> np.ndarray:
        return self._rows[self._start:self._end]

    def samples(self, lo: int, hi: int) -> ImuSamples:
        """A copy of samples [lo, hi) (indices into ``t``) as ImuSamples (orientation None when all NaN)."""
        rows = self.rows[lo:hi].copy()
        ori = rows[:, 6:10]
        return ImuSamples(self.t[lo:hi].copy(), rows[:, 0:3], rows[:, 3:6], None if np.isnan(ori).all() else ori)


class ClipBuffer:
    """Collects frames and IMU samples; ``add_image``/``add_imu`` return the clips and drops they caused.

    Deterministic: the output depends only on the order and stamps of the inputs, never on wall-clock time.
    ``counts`` tallies drops by reason and ``clips`` the emitted clips. ``imu_lead``: s of IMU a complete clip waits for
    beyond its last frame (in its history), so that the rig's estimated time offset can be applied to it
    (``StreamEstimator.imu_lead``, set by the pipeline after each clip).
    """

    def __init__(self, options: ClipBufferOptions | None = None) -> None:
        self.options = options or ClipBufferOptions()
        self._imu = _ImuRing(self.options.imu_buffer)
        self._last_imu_ns: int | None = None
        self._open: list[_Open] = []
        self._pending: collections.deque[RawClip] = collections.deque()
        self._frame_no = 0  # input frames since the last (re)start
        self._last_image_ns: int | None = None
        self._last_image_t = 0.0  # IMU time of the last frame (s), valid when _last_image_ns is set
        self._intervals: collections.deque[float] = collections.deque(maxlen=16)
        self._next_index = 0
        self.counts: collections.Counter[str] = collections.Counter()
        self.imu_lead = 0.0
        self.clips = 0

    # ---- inputs ---------------------------------------------------------------------------------------------

    def add_imu(self, stamp_ns: int, gyro, accel, orientation=None) -> list[RawClip | Drop]:
        """One IMU sample: stamp int ns (IMU time), gyro [3] rad/s, accel [3] m/s^2, orientation [4] xyzw or None.

        Non-finite values are kept (validation downstream turns them into a clip status with a reason).
        O(1) amortised: nothing is copied unless a clip is released."""
        stamp_ns = int(stamp_ns)
        t = stamp_ns * 1e-9
        last = self._last_imu_ns
        if last is not None and stamp_ns <= last:
            reason = "imu_duplicate" if stamp_ns == last else "imu_out_of_order"
            return [self._drop(reason, t, stamp_ns, f"IMU stamp {stamp_ns} ns is not after the previous {last} ns")]
        self._imu.append(t, np.asarray(gyro, np.float64).reshape(3), np.asarray(accel, np.float64).reshape(3),
                         np.nan if orientation is None else np.asarray(orientation, np.float64).reshape(4))
        self._last_imu_ns = stamp_ns
        return self._release()

    def add_image(self, t_cam_ns: int, image: np.ndarray) -> list[RawClip | Drop]:
        """One camera frame with its message stamp (int ns, camera time) and image (kept by reference)."""
        t_cam_ns = int(t_cam_ns)
        t = t_cam_ns * 1e-9 + self.options.time_offset
        out: list[RawClip | Drop] = []
        last_ns = self._last_image_ns
        if last_ns is not None and t_cam_ns <= last_ns:
            reason = "image_duplicate" if t_cam_ns == last_ns else "image_out_of_order"
            return [self._drop(reason, t, t_cam_ns, f"frame stamp {t_cam_ns} ns is not after the previous "
                               f"{last_ns} ns")]
        if last_ns is not None:
            gap, limit = t - self._last_image_t, self._gap_limit()
            if limit is not None and gap > limit:
                out += self._restart(t, t_cam_ns, f"frame gap of {gap:.3f} s before t={t:.6f} s exceeds "
                                     f"{limit:.3f} s")
            else:
                self._intervals.append(gap)
        self._last_image_ns, self._last_image_t = t_cam_ns, t
        o = self.options
        if self._frame_no % o.clip_hop == 0:
            self._open.append(_Open(start=self._frame_no))
        done = []
        for clip in self._open:
            if (self._frame_no - clip.start) % o.stride == 0:
                clip.stamps.append(t)
                clip.stamps_ns.append(t_cam_ns)
                clip.images.append(image)
                if len(clip.stamps) == o.clip_length:
                    done.append(clip)
        for clip in done:
            self._open.remove(clip)
            out += self._complete(clip)
        self._frame_no += 1
        out += self._expire(t)
        return out + self._release()

    def imu_since(self, t: float) -> ImuSamples | None:
        """A copy of the buffered IMU from the last sample at or before ``t`` s (IMU time; from the oldest when none
        is) to the newest; None while the buffer is empty."""
        times = self._imu.t
        if not len(times):
            return None
        return self._imu.samples(max(int(np.searchsorted(times, t, side="right")) - 1, 0), len(times))

    def last_stamp_ns(self) -> int:
        """The newest message stamp taken (camera or IMU, int ns; 0 before any)."""
        return max(self._last_image_ns or 0, self._last_imu_ns or 0)

    # ---- internals ------------------------------------------------------------------------------------------

    def _drop(self, reason: str, t: float, stamp_ns: int, detail: str, clip: int = -1) -> Drop:
        self.counts[reason] += 1
        return Drop(reason, t, stamp_ns, detail, clip)

    def _clip_drop(self, reason: str, clip: RawClip, i: int, detail: str) -> Drop:
        """A drop of waiting clip ``clip``, stamped with its frame ``i``."""
        return self._drop(reason, float(clip.stamps[i]), int(clip.stamps_ns[i]), detail, clip.index)

    def _gap_limit(self) -> float | None:
        if self.options.max_frame_gap > 0:
            return self.options.max_frame_gap
        if len(self._intervals) < 2:
            return None
        return 1.5 * float(np.median(self._intervals))  # one dropped frame (2x) restarts

    def _restart(self, t: float, stamp_ns: int, detail: str) -> list[Drop]:
        drops = [self._drop("frame_gap", t, stamp_ns, f"{detail}; open clip from t={c.stamps[0]:.6f} s dropped")
                 for c in self._open if c.stamps]
        if not drops:
            self.counts["frame_gap"] += 1  # a gap with nothing to drop still counts as a restart
        self._open.clear()
        self._frame_no = 0
        return drops

    def _complete(self, clip: _Open) -> list[Drop]:
        index = self._next_index
        self._next_index += 1
        self._pending.append(RawClip(index, np.array(clip.stamps), np.array(clip.stamps_ns, dtype=np.int64),
                                     tuple(clip.images), ImuSamples(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))))
        drops = []
        while len(self._pending) > self.options.max_pending:
            drops.append(self._clip_drop("frame_overflow", self._pending.popleft(), -1,
                                         f"more than {self.options.max_pending} clips waiting for IMU"))
        return drops

    def _expire(self, t_now: float) -> list[Drop]:
        """Drop waiting clips whose IMU has not arrived ``imu_timeout`` s after their last frame."""
        drops = []
        while self._pending and t_now - self._pending[0].stamps[-1] > self.options.imu_timeout:
            clip = self._pending.popleft()
            newest = f"{self._imu.t[-1]:.6f} s" if len(self._imu) else "none"
            drops.append(self._clip_drop("imu_stalled", clip, -1, f"no IMU past t={clip.stamps[-1]:.6f} s after "
                                         f"{self.options.imu_timeout:.3f} s (newest IMU: {newest})"))
        return drops

    def _release(self) -> list[RawClip | Drop]:
        """Emit waiting clips (in order) whose IMU is complete. O(1) while the oldest clip still waits: it needs
        ``imu_margin`` samples after its last frame, i.e. the margin-th newest sample past that frame."""
        out: list[RawClip | Drop] = []
        m = self.options.imu_margin
        t = self._imu.t
        lead = self.imu_lead
        while self._pending and len(t) >= m and t[-m] > self._pending[0].stamps[-1] + lead:
            clip = self._pending.popleft()
            t0, t1 = float(clip.stamps[0]), float(clip.stamps[-1])
            i0, i1 = window_bounds(t, t0, t1, m)  # the evaluation's rule: a sample at or before t0 is enough
            if t[i0] > t0:
                out.append(self._clip_drop("imu_missing", clip, 0, f"IMU buffer starts at {t[0]:.6f} s, after the "
                                           f"clip's first frame at {t0:.6f} s (needs a sample at or before it)"))
                continue
            hist = None
            if self.options.imu_history > 0:
                h0 = min(i0, max(int(np.searchsorted(t, t0 - self.options.imu_history, side="right")) - 1, 0))
                hist = self._imu.samples(h0, window_bounds(t, t0, t1 + lead, m)[1])
            self.clips += 1
            out.append(RawClip(clip.index, clip.stamps, clip.stamps_ns, clip.images, self._imu.samples(i0, i1), hist))
        return out
