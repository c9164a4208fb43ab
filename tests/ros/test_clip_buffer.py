"""ClipBuffer: frame selection, IMU coverage, time offset and every fault path, on synthetic stamp streams
(the replay tests drive the same buffer with real generated bags)."""

from __future__ import annotations

import numpy as np
import pytest

from vi3_core.errors import DataError
from vi3_core.types import ImuSamples
from vi3_ros.clip_buffer import ClipBuffer, ClipBufferOptions, Drop, RawClip

CAM_DT_NS = 50_000_000  # 20 Hz
IMU_DT = 0.005  # 200 Hz


def _events(seconds: float, *, cam_t0: float = 1.0, imu_t0: float = 0.9, skip_frames=(), imu_until=None):
    """Time-ordered (t s, "img" | "imu", stamp ns) events like a bag."""
    ev = []
    n_img = int(seconds / (CAM_DT_NS * 1e-9))
    for i in range(n_img):
        if i not in skip_frames:
            ev.append((cam_t0 + i * CAM_DT_NS * 1e-9, "img", int(round(cam_t0 * 1e9)) + i * CAM_DT_NS))
    end = cam_t0 + seconds + 0.2 if imu_until is None else imu_until
    for t in np.arange(imu_t0, end, IMU_DT):
        ev.append((float(t), "imu", int(round(t * 1e9))))
    ev.sort(key=lambda e: (e[0], e[1] == "img"))
    return ev


def _run(buf: ClipBuffer, events) -> list[RawClip | Drop]:
    out = []
    for _, kind, v in events:
        if kind == "img":
            out += buf.add_image(v, np.full((4, 6), v % 251, np.uint8))
        else:
            out += buf.add_imu(v, [0.0, 0.0, 0.1], [9.81, 0.0, 0.0])
    return out


def _clips(out):
    return [o for o in out if isinstance(o, RawClip)]


def test_non_overlapping_clips_cover_imu():
    buf = ClipBuffer(ClipBufferOptions(clip_length=8, stride=2))
    clips = _clips(_run(buf, _events(4.0)))
    assert len(clips) == 80 // 16
    for k, c in enumerate(clips):
        assert c.index == k
        assert len(c.images) == 8
        np.testing.assert_allclose(np.diff(c.stamps), 0.1, atol=1e-9)
        assert c.imu.t[0] < c.stamps[0] and c.imu.t[-1] > c.stamps[-1]
        assert c.imu.t[1] >= c.stamps[0] and c.imu.t[-2] <= c.stamps[-1]  # exactly one margin sample each side
    np.testing.assert_allclose(clips[1].stamps[0] - clips[0].stamps[0], 16 * 0.05, atol=1e-9)
    assert buf.clips == len(clips) and not buf.counts


def test_hop_gives_overlapping_clips():
    buf = ClipBuffer(ClipBufferOptions(clip_length=4, stride=1, hop=2))
    clips = _clips(_run(buf, _events(1.0)))
    starts = np.array([c.stamps[0] for c in clips])
    np.testing.assert_allclose(np.diff(starts), 0.1, atol=1e-9)
    assert len(clips) == (20 - 4) // 2 + 1


def test_time_offset_applied_at_edge():
    buf = ClipBuffer(ClipBufferOptions(clip_length=3, stride=1, time_offset=0.013))
    c = _clips(_run(buf, _events(0.5)))[0]
    np.testing.assert_allclose(c.stamps - c.stamps_ns * 1e-9, 0.013, atol=1e-9)
    assert c.imu.t[0] < c.stamps[0] < c.imu.t[1]


def test_images_before_imu_and_late_imu():
    # IMU starts 0.3 s after the first frame: the first clip cannot be covered, later ones are.
    buf = ClipBuffer(ClipBufferOptions(clip_length=4, stride=1))
    out = _run(buf, _events(1.0, imu_t0=1.3))
    drops = [o for o in out if isinstance(o, Drop)]
    assert [d.reason for d in drops] == ["imu_missing"] * len(drops) and drops[0].clip == 0
    clips = _clips(out)
    assert clips and all(c.stamps[0] > 1.3 for c in clips)
    # IMU that arrives after all the frames (a late IMU topic) still completes the waiting clips, in order.
    buf = ClipBuffer(ClipBufferOptions(clip_length=4, stride=1, imu_timeout=10.0, max_pending=8))
    ev = _events(1.0)
    late = [e for e in ev if e[1] == "img"] + [e for e in ev if e[1] == "imu"]
    clips = _clips(_run(buf, late))
    assert [c.index for c in clips] == list(range(5))


def test_stalled_imu_drops_with_reason_then_recovers():
    buf = ClipBuffer(ClipBufferOptions(clip_length=4, stride=1, imu_timeout=0.3))
    ev = [e for e in _events(3.0) if not (e[1] == "imu" and 1.5 < e[0] < 2.2)]
    out = _run(buf, ev)
    stalled = [o for o in out if isinstance(o, Drop) and o.reason == "imu_stalled"]
    assert stalled and all(1.5 - 0.2 < d.t < 2.2 for d in stalled)
    assert "no IMU past" in stalled[0].detail
    assert any(c.stamps[0] > 2.2 for c in _clips(out))
    assert buf.counts["imu_stalled"] == len(stalled)


def test_dropped_frame_restarts_clip():
    buf = ClipBuffer(ClipBufferOptions(clip_length=4, stride=2))
    out = _run(buf, _events(2.0, skip_frames=(13,)))
    gaps = [o for o in out if isinstance(o, Drop) and o.reason == "frame_gap"]
    assert len(gaps) == 1 and gaps[0].t == pytest.approx(1.7)  # frame 13 (t=1.65) is missing
    clips = _clips(out)
    for c in clips:  # no emitted clip spans the gap
        assert not (c.stamps[0] < 1.65 < c.stamps[-1])
    assert clips[-1].stamps[0] >= 1.7
    # an explicit threshold wider than the gap keeps the clip
    buf = ClipBuffer(ClipBufferOptions(clip_length=4, stride=2, max_frame_gap=0.2))
    assert not [o for o in _run(buf, _events(2.0, skip_frames=(13,))) if isinstance(o, Drop)]


def test_out_of_order_and_duplicates_are_dropped_and_counted():
    buf = ClipBuffer(ClipBufferOptions(clip_length=4, stride=1))
    ev = _events(1.0)
    imgs = [e for e in ev if e[1] == "img"]
    imus = [e for e in ev if e[1] == "imu"]
    ev.insert(ev.index(imgs[5]) + 1, imgs[3])  # an old frame again, after frame 5
    ev.insert(ev.index(imgs[8]) + 1, imgs[8])  # a duplicate of frame 8
    ev.insert(ev.index(imus[40]) + 1, imus[30])  # an old IMU sample
    out = _run(buf, ev)
    assert buf.counts == {"image_out_of_order": 1, "image_duplicate": 1, "imu_out_of_order": 1}
    clips = _clips(out)
    assert len(clips) == 5
    for c in clips:
        assert np.all(np.diff(c.stamps) > 0) and np.all(np.diff(c.imu.t) > 0)


def test_bounded_imu_buffer_and_history():
    buf = ClipBuffer(ClipBufferOptions(clip_length=4, stride=1, imu_buffer=50, imu_history=0.1))
    # all IMU first (a burst), then the frames: only the last 50 samples are kept
    ev = _events(1.0)
    ev = [e for e in ev if e[1] == "imu"] + [e for e in ev if e[1] == "img"]
    out = _run(buf, ev)
    assert len(buf._imu) == 50
    assert all(d.reason in ("imu_missing", "imu_stalled") for d in out if isinstance(d, Drop))
    buf = ClipBuffer(ClipBufferOptions(clip_length=4, stride=1, imu_history=0.1))
    c = _clips(_run(buf, _events(1.0)))[1]
    assert c.imu_history is not None
    assert c.imu_history.t[0] <= c.stamps[0] - 0.1 + 1e-9 and c.imu_history.t[-1] == c.imu.t[-1]


def test_nan_samples_pass_through_and_orientation_kept():
    buf = ClipBuffer(ClipBufferOptions(clip_length=3, stride=1))
    out = []
    for k in range(60):
        t = 0.9 + k * IMU_DT
        out += buf.add_imu(int(round(t * 1e9)), [np.nan, 0, 0] if k == 25 else [0, 0, 0], [9.81, 0, 0], [0, 0, 0, 1])
        if k % 10 == 5:
            out += buf.add_image(int(round(t * 1e9)), np.zeros((2, 2), np.uint8))
    c = _clips(out)[0]
    assert np.isnan(c.imu.gyro).any()
    assert c.imu.orientation is not None and np.allclose(c.imu.orientation[:, 3], 1)


def test_options_validated():
    with pytest.raises(DataError, match="stride"):
        ClipBufferOptions(stride=0)


def test_drops_carry_exact_integer_stamps():
    """Drop stamps are the messages' own int ns (float seconds cannot hold ns at epoch magnitudes)."""
    t0 = 1_403_636_579_763_555_584  # EuRoC MH_01's first frame
    buf = ClipBuffer(ClipBufferOptions(clip_length=2, stride=1, imu_timeout=0.01, time_offset=0.003))
    img = np.zeros((2, 2), np.uint8)
    imu_ns = t0 - 3_333_333
    assert not buf.add_imu(imu_ns, [0, 0, 0], [0, 0, 9.81])
    (dup,) = buf.add_imu(imu_ns, [0, 0, 0], [0, 0, 9.81])
    assert (dup.reason, dup.stamp_ns) == ("imu_duplicate", imu_ns)
    assert buf.add_image(t0, img) == [] and buf.add_image(t0 + 50_000_001, img) == []  # a clip waits for IMU
    (old,) = buf.add_image(t0 + 1, img)
    assert (old.reason, old.stamp_ns) == ("image_out_of_order", t0 + 1)
    (stalled,) = [d for d in buf.add_image(t0 + 100_000_003, img) if isinstance(d, Drop)]
    assert (stalled.reason, stalled.clip, stalled.stamp_ns) == ("imu_stalled", 0, t0 + 50_000_001)
    assert stalled.t == pytest.approx((t0 + 50_000_001) * 1e-9 + 0.003)  # float s in IMU time beside it


@pytest.mark.slow
def test_imu_sample_costs_constant_memory_while_a_clip_waits():
    """While a complete clip waits for IMU, a sample is O(1): the IMU buffer is not copied per sample (only when a
    clip is emitted), so a large buffer costs nothing per message."""
    import tracemalloc

    n_samples = 100_000
    buf = ClipBuffer(ClipBufferOptions(clip_length=2, stride=1, imu_buffer=400_000, imu_timeout=60.0))
    for k in range(n_samples):
        buf.add_imu(k * 5_000_000, [0, 0, 0], [0, 0, 9.81])
    t_frames = (n_samples + 2000) * 5_000_000
    for k in range(2):
        assert buf.add_image(t_frames + k * 50_000_000, np.zeros((2, 2), np.uint8)) == []
    tracemalloc.start()
    try:
        for k in range(n_samples, n_samples + 1000):
            assert buf.add_imu(k * 5_000_000, [0, 0, 0], [0, 0, 9.81]) == []
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 64_000, peak  # a copy of the buffered stamps alone would be 8 bytes x 100k samples
    out = []
    for k in range(n_samples + 1000, n_samples + 2200):  # the IMU catches up: the clip comes out whole
        out += buf.add_imu(k * 5_000_000, [0, 0, 0], [0, 0, 9.81])
    (clip,) = _clips(out)
    assert clip.imu.t[0] < clip.stamps[0] < clip.stamps[-1] < clip.imu.t[-1] and len(clip.imu.t) == 13


def test_imu_starting_exactly_at_the_first_frame_is_one_rule_with_the_evaluation():
    """An IMU whose first sample has the first frame's stamp covers the clip (as ``ImuSamples.window`` in the
    evaluation); one that starts a sample later is ``imu_missing``, said as "after"."""
    out = _run(ClipBuffer(), _events(1.0, cam_t0=1.0, imu_t0=1.0))
    clips = _clips(out)
    assert clips and clips[0].imu.t[0] == clips[0].stamps[0] and not [o for o in out if isinstance(o, Drop)]
    c = clips[0]
    everything = ImuSamples(np.r_[c.imu.t, c.imu.t[-1] + IMU_DT], np.zeros((len(c.imu) + 1, 3)),
                            np.zeros((len(c.imu) + 1, 3)))
    np.testing.assert_array_equal(c.imu.t, everything.window(c.stamps[0], c.stamps[-1]).t)  # the same window
    late = _run(ClipBuffer(), _events(1.0, cam_t0=1.0, imu_t0=1.0 + IMU_DT))
    (drop,) = [o for o in late if isinstance(o, Drop) and o.clip == 0]
    assert drop.reason == "imu_missing" and "after the clip's first frame" in drop.detail
