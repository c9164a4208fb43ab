"""ClipBuffer: frame selection, IMU coverage, time offset and every fault path, on synthetic stamp streams
(the replay tests drive the same buffer with real generated bags)."""

from __future__ import annotations

import numpy as np
import pytest

from vi3_core.errors import DataError
from vi3_core.types import ImuSamples
from vi3_ros.clip_buffer import REWIND_AFTER_NS, ClipBuffer, ClipBufferOptions, Drop, RawClip, Rewind

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


def _frame_numbers(clips, cam_t0: float = 1.0) -> list[list[int]]:
    return [[round((t - cam_t0) / (CAM_DT_NS * 1e-9)) for t in c.stamps] for c in clips]


def test_a_lost_frame_the_stride_skips_changes_nothing_and_one_a_clip_needs_is_replaced_by_the_next():
    """Issue 25: each lost frame used to be a frame_gap that threw the open clip away (one corrupt frame in 15
    silenced the node). Frames are numbered by their stamps: a lost odd frame (stride 2 skips it) leaves every clip as
    it was; a lost even one is replaced in its clip by the frame after it; both are counted as image_lost."""
    opts = ClipBufferOptions(clip_length=4, stride=2)
    whole = _frame_numbers(_clips(_run(ClipBuffer(opts), _events(2.0))))
    assert whole[1] == [8, 10, 12, 14]
    buf = ClipBuffer(opts)
    assert _frame_numbers(_clips(_run(buf, _events(2.0, skip_frames=(13,))))) == whole
    assert buf.counts == {"image_lost": 1}
    buf = ClipBuffer(opts)
    out = _run(buf, _events(2.0, skip_frames=(12, 16)))  # a clip's third frame, and the next clip's first
    got = _frame_numbers(_clips(out))
    assert got[1] == [8, 10, 13, 14] and got[2] == [17, 18, 20, 22] and got[3:] == whole[3:]
    assert buf.counts == {"image_lost": 2}
    (lost, _) = [o for o in out if isinstance(o, Drop)]
    assert (lost.reason, lost.count, lost.stamp_ns) == ("image_lost", 1, 1_000_000_000 + 13 * CAM_DT_NS)


def test_up_to_stride_frames_lost_in_a_row_are_bridged_and_more_restart_the_clip():
    opts = ClipBufferOptions(clip_length=4, stride=2)
    buf = ClipBuffer(opts)
    got = _frame_numbers(_clips(_run(buf, _events(2.0, skip_frames=(12, 13)))))
    assert got[1] == [8, 10, 14, 15] and buf.counts == {"image_lost": 2}
    buf = ClipBuffer(opts)
    out = _run(buf, _events(2.0, skip_frames=(11, 12, 13)))
    (gap,) = [o for o in out if isinstance(o, Drop) and o.reason == "frame_gap"]
    assert gap.t == pytest.approx(1.7) and buf.counts == {"image_lost": 3, "frame_gap": 1}
    for c in _clips(out):  # no emitted clip spans the gap
        assert not (c.stamps[0] < 1.55 < c.stamps[-1])
    # an explicit threshold wider than the gap keeps the clip
    buf = ClipBuffer(ClipBufferOptions(clip_length=4, stride=2, max_frame_gap=0.25))
    assert {o.reason for o in _run(buf, _events(2.0, skip_frames=(11, 12, 13))) if isinstance(o, Drop)} == \
        {"image_lost"}


def test_every_tenth_frame_lost_still_gives_every_clip():
    """The live case of issue 25 (every 10th JPEG corrupt: clips_emitted stayed 0 for 20 s): as many clips as
    without losses, each of clip_length frames."""
    opts = ClipBufferOptions(clip_length=8, stride=2)
    whole = _clips(_run(ClipBuffer(opts), _events(10.0)))
    buf = ClipBuffer(opts)
    clips = _clips(_run(buf, _events(10.0, skip_frames=range(9, 190, 10))))
    assert len(clips) == len(whole) and all(len(c.images) == 8 for c in clips)
    assert buf.counts == {"image_lost": 19}


def test_lost_imu_samples_are_counted_from_the_stamps():
    buf = ClipBuffer(ClipBufferOptions(clip_length=4, stride=2))
    ev = _events(2.0)
    imus = [e for e in ev if e[1] == "imu"]
    gone = set(imus[100:103]) | {imus[200]}
    out = _run(buf, [e for e in ev if e not in gone])
    lost = [o for o in out if isinstance(o, Drop) and o.reason == "imu_lost"]
    assert [(d.count, d.stamp_ns) for d in lost] == [(3, imus[103][2]), (1, imus[201][2])]
    assert buf.counts == {"imu_lost": 4} and buf.imu_samples == len(imus) - 4
    assert "3 IMU sample(s) missing" in lost[0].detail and "200.0 Hz" in lost[0].detail


def test_time_going_back_for_good_starts_the_buffer_over_and_a_late_message_does_not():
    """Issue 25: the same seconds again with the same stamps (a looped bag, a restarted driver) were dropped as out
    of order for good. Messages of a stream that keep coming in order behind its newest stamp for REWIND_AFTER_NS are
    a rewind: the buffer starts over (epoch 1; here the IMU's, at 0.9 + 0.25 s, the frames having gone back too) and
    gives clips again; one late message stays a drop."""
    opts = ClipBufferOptions(clip_length=4, stride=2)
    ev = _events(2.0)
    buf = ClipBuffer(opts)
    first = _clips(_run(buf, ev))
    out = _run(buf, ev)  # the same two seconds again
    (rewind,) = [o for o in out if isinstance(o, Rewind)]
    assert rewind.reason == "time_reset" and "imu stamps went back 2.050 s" in rewind.detail
    assert rewind.t == pytest.approx(0.9 + REWIND_AFTER_NS * 1e-9)  # the IMU's first stamp (0.9 s) + 0.25 s
    again = _clips(out)
    assert buf.epoch == 1 and buf.counts["time_reset"] == 1 and len(again) >= len(first) - 1
    assert {c.epoch for c in first} == {0} and {c.epoch for c in again} == {1}
    assert [c.index for c in again] == list(range(len(first), len(first) + len(again)))  # numbers go on
    assert again[0].stamps[0] == pytest.approx(1.2)  # the first frame after the rewind starts a clip
    assert buf.imu_since(0.0).t[0] == pytest.approx(rewind.t)  # nothing of the first pass is left
    assert buf.counts["imu_out_of_order"] == REWIND_AFTER_NS // 5_000_000
    late = ClipBuffer(opts)
    ev = _events(2.0)
    imus = [e for e in ev if e[1] == "imu"]
    ev.insert(ev.index(imus[300]) + 1, imus[100])  # one sample 1 s late
    assert len(_clips(_run(late, ev))) == len(first) and late.epoch == 0 and late.counts == {"imu_out_of_order": 1}


def test_a_loop_seam_with_the_imu_arriving_late_resets_once():
    """As the node receives a looped bag when its callbacks are behind: the IMU a second behind the frames. The frames
    go back first; the old IMU that still arrives after that is dropped as from before the reset (it is not taken as
    the new time, which would reset again when the IMU goes back), and the new IMU is taken as it comes."""
    ev = _events(4.0)
    seam = [(t + (4.5 if loop else 0.0), kind, v) for loop in (0, 1) for t, kind, v in ev]
    late = sorted(seam, key=lambda e: (e[0] + (1.0 if e[1] == "imu" else 0.0), e[1] == "img"))
    buf = ClipBuffer()
    out = _run(buf, late)
    (rewind,) = [o for o in out if isinstance(o, Rewind)]
    assert rewind.detail.startswith("image stamps went back") and buf.epoch == 1
    stale = [o for o in out if isinstance(o, Drop) and "from before time went back" in o.detail]
    assert stale and all(o.reason == "imu_out_of_order" and o.t > 4.0 for o in stale)
    clips = _clips(out)
    passes = [[c for c in clips if c.epoch == e] for e in (0, 1)]
    assert len(passes[0]) == 4 and len(passes[1]) == len(_clips(_run(ClipBuffer(), ev))) - 1
    assert [o.clip for o in out if isinstance(o, Drop) and o.clip >= 0] == [4]  # the one waiting for the old IMU


def test_a_clip_waiting_for_imu_when_time_goes_back_is_skipped_with_the_reason():
    buf = ClipBuffer(ClipBufferOptions(clip_length=4, stride=1, imu_timeout=10.0))
    ev = _events(1.0)
    imus = [e for e in ev if e[1] == "imu"]
    _run(buf, [e for e in ev if e[0] < (1.4 if e[1] == "img" else 1.34)])  # the second clip (to t=1.35) waits...
    out = _run(buf, [e for e in imus if e[0] < 1.3])  # ...when the IMU goes back to its start for good
    (skipped,) = [o for o in out if isinstance(o, Drop) and o.clip >= 0]
    assert (skipped.reason, skipped.clip) == ("time_reset", 1) and "waiting for IMU" in skipped.detail
    assert buf.counts["time_reset"] == 1


def test_an_imu_that_arrives_a_second_late_but_keeps_arriving_is_waited_for():
    """In the node the executor takes one message per subscription in turn, so when it falls behind the images' short
    queue drains before the IMU's long one and the IMU arrives up to the callbacks' delay after the frames (1.4 s
    measured beside a busy process). That is no stall: every clip is emitted (it used to be imu_stalled after 0.5 s)."""
    ev = _events(6.0)
    late = sorted(ev, key=lambda e: (e[0] + (1.0 if e[1] == "imu" else 0.0), e[1] == "img"))
    buf = ClipBuffer()
    clips = _clips(_run(buf, late))
    assert len(clips) == len(_clips(_run(ClipBuffer(), ev))) and not buf.counts


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


def test_clip_imu_carries_the_integer_ns_stamps():
    c = _clips(_run(ClipBuffer(ClipBufferOptions(clip_length=4, stride=2)), _events(1.0)))[0]
    assert c.imu.t_ns is not None and c.imu.t_ns.dtype == np.int64
    np.testing.assert_array_equal(c.imu.t_ns, np.round(c.imu.t * 1e9).astype(np.int64))
