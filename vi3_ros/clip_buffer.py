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
- ``imu_missing``: the IMU buffer does not reach back to the clip's first frame (IMU started late, or the
  bounded buffer overflowed);
- ``imu_stalled``: no IMU past the clip's last frame ``imu_timeout`` seconds (camera time) after it;
- ``frame_overflow``: more clips waiting for IMU than ``max_pending`` (the oldest is dropped).
"""

from __future__ import annotations

import collections
from dataclasses import dataclass, field

import numpy as np

from vi3_core.errors import DataError
from vi3_core.types import ImuSamples


@dataclass(frozen=True)
class ClipBufferOptions:
    """n: frames per clip; stride: take every stride-th input frame; hop: input frames between clip starts (None:
    n * stride, non-overlapping); max_frame_gap: s, larger gap between consecutive input frames restarts collection
    (<= 0: automatic, 1.5 x the median of the recent frame intervals); time_offset: s, t_imu = t_cam + time_offset;
    imu_margin: IMU samples needed beyond the last frame; imu_capacity: bounded IMU buffer (samples);
    imu_timeout: s of camera time a complete clip waits for IMU before it is dropped; history: s of IMU kept before
    the clip's first frame in ``RawClip.imu_history`` (long-window gravity seed; 0 = none); max_pending: complete
    clips waiting for IMU."""

    n: int = 8
    stride: int = 2
    hop: int | None = None
    max_frame_gap: float = 0.0
    time_offset: float = 0.0
    imu_margin: int = 1
    imu_capacity: int = 4000
    imu_timeout: float = 0.5
    history: float = 0.0
    max_pending: int = 4

    def __post_init__(self) -> None:
        checks = {"n >= 2": self.n >= 2, "stride >= 1": self.stride >= 1,
                  "hop >= 1": self.hop is None or self.hop >= 1, "imu_margin >= 1": self.imu_margin >= 1,
                  "imu_capacity >= 16": self.imu_capacity >= 16, "imu_timeout > 0": self.imu_timeout > 0,
                  "history >= 0": self.history >= 0, "max_pending >= 1": self.max_pending >= 1}
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise DataError(f"ClipBufferOptions: {', '.join(bad)} violated by {self}")

    @property
    def clip_hop(self) -> int:
        return self.hop if self.hop is not None else self.n * self.stride


@dataclass(frozen=True)
class RawClip:
    """n frames as recorded plus the IMU covering them.

    index: running clip number (0, 1, ...); stamps: [n] float64 s in IMU time; stamps_ns: [n] the frames' original
    message stamps (camera time, int ns, for the output headers); images: the n raw (distorted) frames as given;
    imu: samples covering [stamps[0], stamps[-1]] plus ``imu_margin`` samples each side; imu_history: samples from
    ``history`` s before stamps[0] to the end of ``imu`` (None when history is 0).
    """

    index: int
    stamps: np.ndarray
    stamps_ns: np.ndarray
    images: tuple[np.ndarray, ...]
    imu: ImuSamples
    imu_history: ImuSamples | None = None


@dataclass(frozen=True)
class Drop:
    """A message or clip that was discarded: ``reason`` is one of the names in the module docstring, ``t`` the
    stamp concerned (s, IMU time for clips), ``detail`` a human-readable sentence, ``clip`` the clip index or -1."""

    reason: str
    t: float
    detail: str
    clip: int = -1


@dataclass
class _Open:
    start: int  # input frame number of the first frame
    stamps: list[float] = field(default_factory=list)
    stamps_ns: list[int] = field(default_factory=list)
    images: list[np.ndarray] = field(default_factory=list)


class ClipBuffer:
    """Collects frames and IMU samples; ``add_image``/``add_imu`` return the clips and drops they caused.

    Deterministic: the output depends only on the order and stamps of the inputs, never on wall-clock time.
    ``counts`` tallies drops by reason and ``clips`` the emitted clips.
    """

    def __init__(self, options: ClipBufferOptions | None = None) -> None:
        self.options = options or ClipBufferOptions()
        cap = self.options.imu_capacity
        self._imu_t: collections.deque[float] = collections.deque(maxlen=cap)
        self._imu_rows: collections.deque[np.ndarray] = collections.deque(maxlen=cap)  # [10]: gyro, accel, quat
        self._open: list[_Open] = []
        self._pending: collections.deque[RawClip] = collections.deque()
        self._frame_no = 0  # input frames since the last (re)start
        self._last_image_t: float | None = None
        self._intervals: collections.deque[float] = collections.deque(maxlen=16)
        self._next_index = 0
        self.counts: collections.Counter[str] = collections.Counter()
        self.clips = 0

    # ---- inputs ---------------------------------------------------------------------------------------------

    def add_imu(self, t: float, gyro, accel, orientation=None) -> list[RawClip | Drop]:
        """One IMU sample: t s (IMU time), gyro [3] rad/s, accel [3] m/s^2, orientation [4] xyzw or None.

        Non-finite values are kept (validation downstream turns them into a clip status with a reason)."""
        t = float(t)
        if self._imu_t and t <= self._imu_t[-1]:
            reason = "imu_duplicate" if t == self._imu_t[-1] else "imu_out_of_order"
            return [self._drop(reason, t, f"IMU stamp {t:.9f} s is not after the previous {self._imu_t[-1]:.9f} s")]
        ori = np.full(4, np.nan) if orientation is None else np.asarray(orientation, dtype=np.float64).reshape(4)
        self._imu_t.append(t)
        self._imu_rows.append(np.concatenate([np.asarray(gyro, np.float64).reshape(3),
                                              np.asarray(accel, np.float64).reshape(3), ori]))
        return self._release()

    def add_image(self, t_cam_ns: int, image: np.ndarray) -> list[RawClip | Drop]:
        """One camera frame with its message stamp (int ns, camera time) and image (kept by reference)."""
        t_cam_ns = int(t_cam_ns)
        t = t_cam_ns * 1e-9 + self.options.time_offset
        out: list[RawClip | Drop] = []
        last = self._last_image_t
        if last is not None and t <= last:
            reason = "image_duplicate" if t == last else "image_out_of_order"
            return [self._drop(reason, t, f"frame stamp {t:.9f} s is not after the previous {last:.9f} s")]
        if last is not None:
            gap, limit = t - last, self._gap_limit()
            if limit is not None and gap > limit:
                out += self._restart(t, f"frame gap of {gap:.3f} s before t={t:.6f} s exceeds {limit:.3f} s")
            else:
                self._intervals.append(gap)
        self._last_image_t = t
        o = self.options
        if self._frame_no % o.clip_hop == 0:
            self._open.append(_Open(start=self._frame_no))
        done = []
        for clip in self._open:
            if (self._frame_no - clip.start) % o.stride == 0:
                clip.stamps.append(t)
                clip.stamps_ns.append(t_cam_ns)
                clip.images.append(image)
                if len(clip.stamps) == o.n:
                    done.append(clip)
        for clip in done:
            self._open.remove(clip)
            out += self._complete(clip)
        self._frame_no += 1
        out += self._expire(t)
        return out + self._release()

    # ---- internals ------------------------------------------------------------------------------------------

    def _drop(self, reason: str, t: float, detail: str, clip: int = -1) -> Drop:
        self.counts[reason] += 1
        return Drop(reason, t, detail, clip)

    def _gap_limit(self) -> float | None:
        if self.options.max_frame_gap > 0:
            return self.options.max_frame_gap
        if len(self._intervals) < 2:
            return None
        return 1.5 * float(np.median(self._intervals))  # one dropped frame (2x) restarts

    def _restart(self, t: float, detail: str) -> list[Drop]:
        drops = [self._drop("frame_gap", t, f"{detail}; open clip from t={c.stamps[0]:.6f} s dropped")
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
            old = self._pending.popleft()
            drops.append(self._drop("frame_overflow", float(old.stamps[-1]),
                                    f"more than {self.options.max_pending} clips waiting for IMU", old.index))
        return drops

    def _expire(self, t_now: float) -> list[Drop]:
        """Drop waiting clips whose IMU has not arrived ``imu_timeout`` s after their last frame."""
        drops = []
        while self._pending and t_now - self._pending[0].stamps[-1] > self.options.imu_timeout:
            clip = self._pending.popleft()
            newest = f"{self._imu_t[-1]:.6f} s" if self._imu_t else "none"
            drops.append(self._drop("imu_stalled", float(clip.stamps[-1]),
                                    f"no IMU past t={clip.stamps[-1]:.6f} s after {self.options.imu_timeout:.3f} s "
                                    f"(newest IMU: {newest})", clip.index))
        return drops

    def _release(self) -> list[RawClip | Drop]:
        """Emit waiting clips (in order) whose IMU is complete."""
        out: list[RawClip | Drop] = []
        m = self.options.imu_margin
        while self._pending and self._imu_t:
            clip = self._pending[0]
            t0, t1 = float(clip.stamps[0]), float(clip.stamps[-1])
            t = np.fromiter(self._imu_t, dtype=np.float64, count=len(self._imu_t))
            i1 = int(np.searchsorted(t, t1, side="right"))
            if len(t) - i1 < m:
                break  # wait for more IMU
            self._pending.popleft()
            i0 = int(np.searchsorted(t, t0, side="left"))
            if i0 < m:
                out.append(self._drop("imu_missing", t0, f"IMU buffer starts at {t[0]:.6f} s, after the clip's "
                                      f"first frame at {t0:.6f} s (needs {m} sample(s) before)", clip.index))
                continue
            h0 = i0 - m
            if self.options.history > 0:
                h0 = min(h0, int(np.searchsorted(t, t0 - self.options.history, side="left")))
            rows = np.stack([self._imu_rows[i] for i in range(h0, i1 + m)])
            imu = _samples(t[i0 - m:i1 + m], rows[i0 - m - h0:])
            hist = _samples(t[h0:i1 + m], rows) if self.options.history > 0 else None
            self.clips += 1
            out.append(RawClip(clip.index, clip.stamps, clip.stamps_ns, clip.images, imu, hist))
        return out


def _samples(t: np.ndarray, rows: np.ndarray) -> ImuSamples:
    ori = rows[:, 6:10]
    return ImuSamples(t, rows[:, 0:3], rows[:, 3:6], None if np.isnan(ori).all() else ori)
