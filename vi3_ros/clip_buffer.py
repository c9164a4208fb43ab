"""Clip buffering: turn a live stream of camera frames and IMU samples into clips of n frames.

Pure Python/numpy, no ROS: the node feeds it from its subscriptions and the replay tool from a bag, so both
produce exactly the same clips.

Time base. Every stamp inside the buffer is in IMU time. Camera stamps are shifted at the edge,
``t_imu = t_cam + time_offset`` (Kalibr's ``timeshift_cam_imu`` convention), so ``add_image`` takes the
message stamp and the clip's ``stamps`` are already corrected (``Clip.stamps`` is documented that way).

Frame selection. Input frames are numbered by their stamps from the last (re)start: a frame that never arrived (lost
in transport, or dropped before the buffer as undecodable) keeps its number, counted from the gap it leaves against
the median recent frame interval. A clip starts every ``hop`` frames (default ``n * stride``: non-overlapping) and
takes every ``stride``-th frame from its start until it has ``n`` frames: each arriving frame whose number has
reached the clip's next slot (start + stride x the frames it has). The rule for lost frames that follows: one that the
stride skips changes nothing; when one that a clip needs is lost, the next frame that arrives takes its place (a frame
late; the clip's later frames stay on the stride unless that frame was one of them), so the clip keeps its ``n``
frames and, with ``shared_frames``, still shares its last frame with the next clip.
Only a gap longer than ``max_frame_gap`` (automatic: ``stride`` + 1.5 median intervals, so up to ``stride`` frames
lost in a row are bridged) restarts collection. A clip is emitted once the IMU reaches ``imu_margin`` samples past its
last frame (interpolation and preintegration need a sample on each side). Faults become ``Drop`` events with a named
``reason``:

- ``image_out_of_order`` / ``image_duplicate`` / ``imu_out_of_order`` / ``imu_duplicate``: the message is dropped;
- ``image_lost`` / ``imu_lost``: frames or IMU samples missing from the stamps (a gap of k median intervals counts
  k - 1; ``Drop.count``), whatever the cause (never received, or dropped before the buffer as malformed);
- ``frame_gap``: two consecutive frames further apart than ``max_frame_gap``; open clips are dropped and
  collection restarts at the new frame;
- ``imu_missing``: the IMU buffer does not reach back to the clip's first frame, i.e. has no sample at or before
  it (IMU started late, or the bounded buffer overflowed); the clip's IMU is ``vi3_core.types.window_bounds``'s
  window, as in the evaluation;
- ``imu_stalled``: no IMU past the clip's last frame, and no IMU sample arrived at all, for ``imu_timeout`` seconds of
  camera time after it (an IMU that arrives late but keeps arriving, as in a node whose callbacks fall behind and
  take the images' short queue faster than the IMU's long one, is waited for, up to ``max_pending`` clips);
- ``frame_overflow``: more clips waiting for IMU than ``max_pending`` (the oldest is dropped);
- ``time_reset`` (a ``Rewind``): the stamps of one stream went back and stayed back: its messages kept coming, in
  order, behind its newest stamp over ``REWIND_AFTER_NS`` (a looped or replayed recording, a restarted driver or
  simulator). Until then each is ``*_out_of_order``; then the buffer forgets both streams and starts over with that
  message (``epoch`` counts the resets, each clip carries the epoch it was emitted in), and clips waiting for IMU are
  skipped with that reason. Messages of the other stream that are still of the old time (a node's IMU arrives behind
  its images) are ``*_out_of_order`` until that stream has gone back too. A single late message never resets.

Cost. An IMU sample is O(1) amortised: samples go into preallocated arrays, and arrays are cut out only when a clip
is emitted. Stamps are int ns at the inputs, in ``Drop.stamp_ns`` and ``ImuSamples.t_ns`` (exact), float64 s (IMU
time) inside.
"""

from __future__ import annotations

import collections
import dataclasses
import statistics
from dataclasses import dataclass, field

import numpy as np

from vi3_core.errors import DataError
from vi3_core.types import CLIP_LENGTH, CLIP_STRIDE, ImuSamples, window_bounds


def missing_in_gap(gap: float, interval: float) -> int:
    """Messages missing in a gap of ``gap`` between two received ones at the nominal ``interval`` (same unit): a gap
    of k intervals (more than 1.5) counts k - 1."""
    return round(gap / interval) - 1 if gap > 1.5 * interval else 0


@dataclass(frozen=True)
class ClipBufferOptions:
    """clip_length: frames per clip (n); stride: take every stride-th input frame; hop: input frames between clip starts
    (None: clip_length * stride, non-overlapping); max_frame_gap: s, larger gap between consecutive input frames
    restarts collection (<= 0: automatic, stride + 1.5 times the median of the recent frame intervals); time_offset: s,
    t_imu = t_cam + time_offset; imu_margin: IMU samples needed beyond the last frame; imu_buffer: bounded IMU buffer
    (samples); imu_timeout: s of camera time a complete clip waits for IMU, with no IMU sample arriving, before it is
    dropped; imu_history: s of IMU kept before the clip's first frame in ``RawClip.imu_history`` (long-window gravity
    seed; 0 = none), which also reaches ``ClipBuffer.imu_lead`` s beyond its last frame; max_pending: complete clips
    waiting for IMU."""

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
    is 0); epoch: the buffer's ``epoch`` when the clip was emitted (how many times time went back before it).
    """

    index: int
    stamps: np.ndarray
    stamps_ns: np.ndarray
    images: tuple[np.ndarray, ...]
    imu: ImuSamples
    imu_history: ImuSamples | None = None
    epoch: int = 0


@dataclass(frozen=True)
class Drop:
    """A message or clip that was discarded: ``reason`` is one of the names in the module docstring; the stamp
    concerned as ``t`` (float64 s, IMU time) and ``stamp_ns`` (the message's own header stamp, int ns, exact: camera
    time for frames and clips, IMU time for IMU samples); ``detail`` a human-readable sentence; ``clip`` the clip
    index or -1; ``count`` the messages it stands for (``image_lost`` / ``imu_lost``: the missing ones)."""

    reason: str
    t: float
    stamp_ns: int
    detail: str
    clip: int = -1
    count: int = 1


@dataclass(frozen=True)
class Rewind(Drop):
    """``time_reset``: time went back for good and the buffer started over (see the module docstring); ``stamp_ns``
    is the message it starts over with."""


#: ns of their own stamps that messages must keep coming behind the newest stamp, in order, before time counts as
#: gone back (``Rewind``); and at least this many messages.
REWIND_AFTER_NS = 250_000_000
REWIND_MIN_MESSAGES = 3


@dataclass
class _Open:
    start: int  # input frame number of the first frame (on the stride grid; a lost one is replaced by the next)
    stamps: list[float] = field(default_factory=list)
    stamps_ns: list[int] = field(default_factory=list)
    images: list[np.ndarray] = field(default_factory=list)


_ROW = 10  # gyro [3] rad/s, accel [3] m/s^2, orientation [4] xyzw (NaN: none)


class _ImuRing:
    """The newest ``capacity`` IMU samples in preallocated arrays of twice that length: ``append`` is O(1)
    amortised (when the storage end is reached, the kept samples move to the front once per ``capacity`` appends)
    and ``t`` / ``rows`` are contiguous views [len] float64 s and [len,10] (``_ROW``), oldest first, beside the
    stamps as they came [len] int64 ns."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._t = np.empty(2 * capacity)
        self._ns = np.empty(2 * capacity, dtype=np.int64)
        self._rows = np.empty((2 * capacity, _ROW))
        self._start = self._end = 0

    def __len__(self) -> int:
        return self._end - self._start

    def clear(self) -> None:
        self._start = self._end = 0

    def append(self, t_ns: int, gyro, accel, orientation) -> None:
        """One sample: stamp int ns, gyro [3] rad/s, accel [3] m/s^2, orientation [4] xyzw (NaN: none)."""
        if self._end == len(self._t):
            n, kept = len(self), slice(self._start, self._end)
            self._t[:n], self._ns[:n], self._rows[:n] = self._t[kept], self._ns[kept], self._rows[kept]
            self._start, self._end = 0, n
        self._t[self._end] = t_ns * 1e-9
        self._ns[self._end] = t_ns
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
        return ImuSamples(self.t[lo:hi].copy(), rows[:, 0:3], rows[:, 3:6], None if np.isnan(ori).all() else ori,
                          self._ns[self._start:self._end][lo:hi].copy())


class ClipBuffer:
    """Collects frames and IMU samples; ``add_image``/``add_imu`` return the clips and drops they caused.

    Deterministic: the output depends only on the order and stamps of the inputs, never on wall-clock time.
    ``counts`` tallies drops by reason (messages, or clips), ``clips`` the emitted clips, ``imu_samples`` the IMU
    samples taken, ``epoch`` the times time went back (``Rewind``). ``imu_lead``: s of IMU a complete clip waits for
    beyond its last frame (in its history), so that the rig's estimated time offset can be applied to it
    (``StreamEstimator.imu_lead``, set by the pipeline after each clip).
    """

    def __init__(self, options: ClipBufferOptions | None = None) -> None:
        self.options = options or ClipBufferOptions()
        self._imu = _ImuRing(self.options.imu_buffer)
        self._imu_dts: collections.deque[int] = collections.deque(maxlen=16)  # recent IMU intervals, ns
        self._imu_dt_ns = 0  # their median (0: not known yet), refreshed every 16 samples
        self._pending: collections.deque[RawClip] = collections.deque()
        self._intervals: collections.deque[float] = collections.deque(maxlen=16)  # recent frame intervals, s
        self._next_index = 0
        self.counts: collections.Counter[str] = collections.Counter()
        self.imu_lead = 0.0
        self.clips = 0
        self.imu_samples = 0
        self.epoch = 0
        self._start_over()

    def _start_over(self) -> None:
        """Forget both streams' messages and stamps, and the clips being collected (not the rates, counters or clip
        numbers)."""
        self._imu.clear()
        self._last_imu_ns: int | None = None
        self._imu_arrived = -np.inf  # IMU time of the newest frame when the last IMU sample was taken (s)
        self._open: list[_Open] = []
        self._frame_no = 0  # number of the newest frame since the last (re)start, by its stamp
        self._next_start = 0  # frame number at which the next clip starts
        self._last_image_ns: int | None = None
        self._last_image_t = 0.0  # IMU time of the last frame (s), valid when _last_image_ns is set
        self._behind: dict[str, tuple[int, int, int]] = {}  # stream -> (first, last stamp ns, count) of a run behind
        self._stale: dict[str, int] = {}  # stream -> stamp (ns) above which its messages are from before a rewind

    # ---- inputs ---------------------------------------------------------------------------------------------

    def add_imu(self, stamp_ns: int, gyro, accel, orientation=None) -> list[RawClip | Drop]:
        """One IMU sample: stamp int ns (IMU time), gyro [3] rad/s, accel [3] m/s^2, orientation [4] xyzw or None.

        Non-finite values are kept (validation downstream turns them into a clip status with a reason).
        O(1) amortised: nothing is copied unless a clip is released."""
        stamp_ns = int(stamp_ns)
        t = stamp_ns * 1e-9
        out = self._in_order("imu", stamp_ns, t, "IMU stamp")
        if out and not isinstance(out[-1], Rewind):
            return out
        last = self._last_imu_ns
        if last is not None:
            out += self._imu_lost(stamp_ns - last, t, stamp_ns)
        self._imu.append(stamp_ns, np.asarray(gyro, np.float64).reshape(3), np.asarray(accel, np.float64).reshape(3),
                         np.nan if orientation is None else np.asarray(orientation, np.float64).reshape(4))
        self._last_imu_ns = stamp_ns
        self._imu_arrived = self._last_image_t if self._last_image_ns is not None else -np.inf
        self.imu_samples += 1
        return out + self._release()

    def add_image(self, t_cam_ns: int, image: np.ndarray) -> list[RawClip | Drop]:
        """One camera frame with its message stamp (int ns, camera time) and image (kept by reference)."""
        t_cam_ns = int(t_cam_ns)
        t = t_cam_ns * 1e-9 + self.options.time_offset
        out: list[RawClip | Drop] = self._in_order("image", t_cam_ns, t, "frame stamp")
        if out and not isinstance(out[-1], Rewind):
            return out
        if self._last_image_ns is not None:
            gap, interval = t - self._last_image_t, self._frame_interval()
            limit = self._gap_limit(interval)
            lost = missing_in_gap(gap, interval) if interval is not None else 0
            if lost:
                out.append(self._drop("image_lost", t, t_cam_ns, f"{lost} frame(s) missing before t={t:.6f} s "
                                      f"(gap of {gap:.3f} s)", count=lost))
            if limit is not None and gap > limit:
                out += self._restart(t, t_cam_ns, f"frame gap of {gap:.3f} s before t={t:.6f} s exceeds "
                                     f"{limit:.3f} s")
            else:
                self._intervals.append(gap)
                self._frame_no += 1 + lost  # a lost frame keeps its number
        self._last_image_ns, self._last_image_t = t_cam_ns, t
        o = self.options
        if self._frame_no >= self._next_start:  # a clip starts here (at the first frame after a lost start)
            start = self._next_start + (self._frame_no - self._next_start) // o.clip_hop * o.clip_hop
            self._open.append(_Open(start=start))
            self._next_start = start + o.clip_hop
        done = []
        for clip in self._open:
            if self._frame_no >= clip.start + o.stride * len(clip.stamps):  # its next frame, or the one after it
                clip.stamps.append(t)
                clip.stamps_ns.append(t_cam_ns)
                clip.images.append(image)
                if len(clip.stamps) == o.clip_length:
                    done.append(clip)
        for clip in done:
            self._open.remove(clip)
            out += self._complete(clip)
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

    def _drop(self, reason: str, t: float, stamp_ns: int, detail: str, clip: int = -1, count: int = 1) -> Drop:
        self.counts[reason] += count
        return Drop(reason, t, stamp_ns, detail, clip, count)

    def _clip_drop(self, reason: str, clip: RawClip, i: int, detail: str) -> Drop:
        """A drop of waiting clip ``clip``, stamped with its frame ``i``."""
        return self._drop(reason, float(clip.stamps[i]), int(clip.stamps_ns[i]), detail, clip.index)

    def _imu_lost(self, gap_ns: int, t: float, stamp_ns: int) -> list[Drop]:
        """The samples missing before the one at ``stamp_ns``, ``gap_ns`` after the previous (k median intervals:
        k - 1); the interval joins the median, which is refreshed every 16 samples."""
        nominal = self._imu_dt_ns
        self._imu_dts.append(gap_ns)
        if (not nominal and len(self._imu_dts) >= 4) or self.imu_samples % 16 == 0:
            self._imu_dt_ns = int(statistics.median(self._imu_dts))
        lost = missing_in_gap(gap_ns, nominal) if nominal else 0
        if not lost:
            return []
        return [self._drop("imu_lost", t, stamp_ns, f"{lost} IMU sample(s) missing before t={t:.6f} s (gap of "
                           f"{gap_ns * 1e-9:.4f} s at {1e9 / nominal:.1f} Hz)", count=lost)]

    def _frame_interval(self) -> float | None:
        """s: the median recent frame interval (None while fewer than two are known)."""
        return float(statistics.median(self._intervals)) if len(self._intervals) >= 2 else None

    def _gap_limit(self, interval: float | None) -> float | None:
        """s: the largest frame gap bridged, given the median frame ``interval`` (``_frame_interval``)."""
        if self.options.max_frame_gap > 0:
            return self.options.max_frame_gap
        if interval is None:
            return None
        return (self.options.stride + 1.5) * interval  # up to stride frames lost in a row

    def _restart(self, t: float, stamp_ns: int, detail: str) -> list[Drop]:
        drops = [self._drop("frame_gap", t, stamp_ns, f"{detail}; open clip from t={c.stamps[0]:.6f} s dropped")
                 for c in self._open if c.stamps]
        if not drops:
            self.counts["frame_gap"] += 1  # a gap with nothing to drop still counts as a restart
        self._open.clear()
        self._frame_no = self._next_start = 0
        return drops

    def _in_order(self, stream: str, stamp_ns: int, t: float, what: str) -> list[Drop]:
        """Whether the message of ``stream`` ("imu" or "image") at ``stamp_ns`` is taken: [] when it is in order; drops
        when it is not (``*_duplicate``, ``*_out_of_order``); or, when it made time go back (``_went_back``), the
        events of that ending in the ``Rewind``, after which it is taken."""
        stale = self._stale.get(stream)
        if stale is not None and stamp_ns > stale:
            return [self._drop(f"{stream}_out_of_order", t, stamp_ns, f"{what} {stamp_ns} ns is from before time went "
                               "back (this stream has not gone back yet)")]
        self._stale.pop(stream, None)
        last = self._last_imu_ns if stream == "imu" else self._last_image_ns
        if last is None or stamp_ns > last:
            self._behind.pop(stream, None)
            return []
        detail = f"{what} {stamp_ns} ns is not after the previous {last} ns"
        if stamp_ns == last:
            return [self._drop(f"{stream}_duplicate", t, stamp_ns, detail)]
        return self._went_back(stream, stamp_ns, t, last) or [self._drop(f"{stream}_out_of_order", t, stamp_ns, detail)]

    def _went_back(self, stream: str, stamp_ns: int, t: float, last: int) -> list[Drop]:
        """A message of ``stream`` behind its stream's newest stamp ``last``: [] while it may be one late message;
        once such messages kept coming in order over REWIND_AFTER_NS (at least REWIND_MIN_MESSAGES), time went back:
        the buffer starts over, the clips waiting for IMU are skipped, and the ``Rewind`` comes last. The other stream,
        when its newest stamp is nearer the old time than the new, has not gone back yet (a node's IMU arrives behind
        its images): its messages above the midpoint are dropped until one of the new time comes."""
        first, prev, count = self._behind.get(stream, (stamp_ns, stamp_ns, 0))
        if stamp_ns <= prev and count:  # not in order with the run: a new run starts here
            first, count = stamp_ns, 0
        self._behind[stream] = first, stamp_ns, count + 1
        if count + 1 < REWIND_MIN_MESSAGES or stamp_ns - first < REWIND_AFTER_NS:
            return []
        why = (f"{stream} stamps went back {(last - stamp_ns) * 1e-9:.3f} s and stayed back ({count + 1} messages in "
               f"order over {(stamp_ns - first) * 1e-9:.3f} s behind the newest stamp {last} ns: a looped or replayed "
               "recording, a restarted driver or simulator)")
        skipped = [Drop("time_reset", float(c.stamps[-1]), int(c.stamps_ns[-1]), f"{why}; the clip was waiting for "
                        "IMU", c.index) for c in self._pending]
        other = "image" if stream == "imu" else "imu"
        other_last = self._last_image_ns if stream == "imu" else self._last_imu_ns
        self._pending.clear()
        self._start_over()
        midpoint = (last + stamp_ns) // 2
        if other_last is not None and other_last > midpoint:
            self._stale[other] = midpoint
        self.epoch += 1
        self.counts["time_reset"] += 1
        return skipped + [Rewind("time_reset", t, stamp_ns, f"{why}; the buffers start over at {stamp_ns} ns")]

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
        """Drop waiting clips whose IMU has not arrived ``imu_timeout`` s (camera time ``t_now``) after their last
        frame, when no IMU sample arrived meanwhile either."""
        drops = []
        while self._pending and t_now - max(self._pending[0].stamps[-1], self._imu_arrived) > self.options.imu_timeout:
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
            out.append(dataclasses.replace(clip, imu=self._imu.samples(i0, i1), imu_history=hist, epoch=self.epoch))
        return out
