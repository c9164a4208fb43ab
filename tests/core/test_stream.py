"""``StreamEstimator`` with scale links: clips that share a frame with the clip before them link their scales through
it, so a gentle take-off is metric within seconds and stays so; a clip after dropped ones gets the shared frame in
place of its first; every claim stays within its sigma. The flight is the real EuRoC V1_02 trajectory and IMU
(``../shared``), rendered with depth at a quarter of the camera's resolution, and the "backbone" is the evaluation's
ground-truth instrument with a 3DFM's pose and depth noise."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from euroc_cuts import quarter_copy

from vi3_core.backbones import make_backbone
from vi3_core.backbones.ground_truth import GroundTruthPoses
from vi3_core.dataset.asl import read_asl
from vi3_core.dataset.generate import cached_sequence
from vi3_core.dataset.sequence import make_clip, sample_clips
from vi3_core.eval.chained import chained_metrics
from vi3_core.eval.coverage import motion_start
from vi3_core.init import InitOptions
from vi3_core.online import OnlineOptions, StreamEstimator, StreamOptions
from vi3_core.online.calibration import CalibrationOptions
from vi3_core.sim.visual import DepthNoise, PoseNoise

pytestmark = pytest.mark.slow  # renders 14 s of a real flight once (cached), then runs it through the estimator


@pytest.fixture(scope="module")
def takeoff(euroc_v102, cache_dir):
    """V1_02's first 14 s from 2 s in: the slow take-off (motion starts about 1.6 s in) and the first seconds of
    flight."""
    recording = quarter_copy(euroc_v102, cache_dir / "v102_quarter" / "mav0")
    return read_asl(cached_sequence(cache_dir, seconds=14.0, seed=0, from_euroc=recording, start_s=2.0) / "mav0")


def _stream(seq, online: OnlineOptions, *, clips=None, seed: int = 0, calibration: CalibrationOptions | None = None,
            init: InitOptions | None = None) -> tuple[StreamEstimator, list]:
    """The stream after ``clips`` (default: every clip, each sharing its first frame with the one before) and its
    outcomes, each with the instrument's true metres per model unit of its clip."""
    instrument = GroundTruthPoses(noise=PoseNoise(0.003, 0.1), depth_noise=DepthNoise(0.05, 0.02), seed=seed)
    stream = StreamEstimator(instrument, online=online, calibration=calibration, init=init)
    clips = clips if clips is not None else sample_clips(len(seq), mode="sliding", hop=14)
    out = []
    for idx in clips:
        clip = make_clip(seq, idx, history_s=online.online_max_bridge, with_images=False)
        out.append((stream.process(clip), instrument.last_scale))
    return stream, out


def _run(seq, online: OnlineOptions, **kwargs) -> list:
    """The outcomes of ``_stream``."""
    return _stream(seq, online, **kwargs)[1]


def _claims(outcomes, t_from: float) -> tuple[float, list[float], list[float]]:
    """(share of the clips starting after ``t_from`` claimed, the claims' relative errors, their relative sigmas)."""
    later = [(o, truth) for o, truth in outcomes if o.clip.stamps[0] >= t_from]
    ok = [(o.init, truth) for o, truth in later if o.init.ok]
    return (len(ok) / len(later), [abs(init.scale / truth - 1) for init, truth in ok],
            [init.scale_sigma / init.scale for init, _ in ok])


def test_links_make_a_gentle_takeoff_metric_within_seconds_and_every_claim_honest(takeoff):
    start = motion_start(takeoff.gt.t, takeoff.gt.v_WB, float(takeoff.stamps[0]))
    linked = _run(takeoff, OnlineOptions())
    unlinked = _run(takeoff, OnlineOptions(shared_frames=0))
    used = [o.decision.link for o, _ in linked if o.decision.joined]
    assert sum(link is not None for link in used) >= 0.8 * len(used)
    share, _, sigmas = _claims(linked, start + 3.0)
    _, _, sigmas_unlinked = _claims(unlinked, start + 3.0)
    assert share == 1.0  # every clip from 3 s after the start of motion on
    assert np.median(sigmas) < 0.8 * np.median(sigmas_unlinked), (sigmas, sigmas_unlinked)  # the chain tightens them
    first = min(o.clip.stamps[-1] for o, _ in linked if o.init.ok) - start
    assert first <= 4.0, first
    _, errors, sigmas = _claims(linked, -np.inf)
    assert all(e < 0.1 and e < 3 * s for e, s in zip(errors, sigmas)), list(zip(errors, sigmas))
    described = [o.decision.describe() for o, _ in linked if o.decision.link is not None]
    assert all("scale: linked (depth of 1 frame(s) shared with the clip at" in d for d in described)


def test_the_odometry_goes_on_where_a_scale_is_known_too_loosely_to_claim(takeoff):
    """The claim gate at 0.1 % claims no clip. The clips whose window scale settled within odom_max_scale_sigma (10 %)
    are placed in odom all the same, unclaimed (no metric geometry), and that odometry follows the flight to a few
    per cent of its path, as the claimed clips' of the shipped gate do; with odom_max_scale_sigma 0 nothing is
    placed."""
    start = motion_start(takeoff.gt.t, takeoff.gt.v_WB, float(takeoff.stamps[0]))
    tight = InitOptions(max_scale_sigma=0.001)
    stream, loose = _stream(takeoff, OnlineOptions(), init=tight)
    assert not any(o.init.ok for o, _ in loose)
    placed = [o for o, _ in loose if o.chained is not None]
    assert all(o.mode == "none" and o.init.fit.scale_rel_sigma <= 0.1 for o in placed)
    in_flight = [o for o, _ in loose if o.clip.stamps[0] >= start + 3.0]
    assert sum(o.chained is not None for o in in_flight) >= 0.8 * len(in_flight)

    def drift(stream: StreamEstimator) -> float:
        traj = stream.trajectory  # scored per segment, as `vi3 eval` scores it
        return chained_metrics(traj.T_OB, takeoff.gt.at(traj.stamps).T_WB, stamps=traj.stamps,
                               segment_starts=traj.resets).drift_pct

    assert len({o.segment for o in placed}) == 1  # one odom segment through the unclaimed clips

    claimed, _ = _stream(takeoff, OnlineOptions(odom_max_scale_sigma=0.0))  # the claimed clips only, shipped gate
    assert drift(stream) < 3.0 and drift(stream) < drift(claimed) + 1.0, (drift(stream), drift(claimed))
    off = _run(takeoff, OnlineOptions(odom_max_scale_sigma=0.0), init=tight)
    assert all(o.chained is None for o, _ in off)


def test_a_clip_after_dropped_ones_gets_the_shared_frame_in_place_of_its_first(takeoff):
    """Clips 3 and 4 dropped (a busy worker): clip 5 starts 2.1 s after clip 2's last frame. Within shared_max_gap
    clip 2's last frame stands in for clip 5's first and links them; beyond it clip 5 goes unlinked, and says so."""
    clips = sample_clips(len(takeoff), mode="sliding", hop=14)[2:12]
    kept = clips[:1] + clips[3:]
    bridged = _run(takeoff, OnlineOptions(shared_max_gap=3.0), clips=kept)
    after, shared = bridged[1][0], takeoff.stamps[clips[0][-1]]
    assert after.clip.stamps[0] == shared and np.array_equal(after.clip.stamps[1:], takeoff.stamps[clips[3][1:]])
    assert after.decision.link is not None and after.decision.link.clip_start == takeoff.stamps[clips[0][0]]
    assert after.result.base.T_wc.shape[0] == 8
    apart = _run(takeoff, OnlineOptions(shared_max_gap=1.0), clips=kept)
    assert np.array_equal(apart[1][0].clip.stamps, takeoff.stamps[clips[3]]) and apart[1][0].decision.link is None
    assert "does not start with the 1 frame(s) kept" in apart[1][0].decision.link_note
    # the rest of the flight links on as before
    assert sum(o.decision.link is not None for o, _ in bridged[2:]) >= 6


def test_without_shared_frames_the_window_is_todays(takeoff):
    """shared_frames 0, back-to-back clips and no self-calibration: no link, no clip changed, the decisions say nothing
    of links."""
    clips = sample_clips(len(takeoff), mode="sliding")[:6]
    outcomes = _run(takeoff, dataclasses.replace(OnlineOptions(), shared_frames=0), clips=clips,
                    calibration=CalibrationOptions(self_calibration=False))
    assert all(o.decision.link is None and not o.decision.link_note for o, _ in outcomes)
    assert all(np.array_equal(o.clip.stamps, takeoff.stamps[idx]) for (o, _), idx in zip(outcomes, clips))


def test_the_frames_whose_depth_is_read():
    """init mode: the last frame (published) and the shared frames at both ends (the scale links); every frame when
    the outputs publish every frame's depth, in cond / ttr mode (the refinement reads them all), and without online
    only the last."""
    instrument = GroundTruthPoses()
    stream = StreamEstimator(instrument, online=OnlineOptions(shared_frames=2))
    assert stream.depth_frames(8).tolist() == [0, 1, 6, 7]
    assert StreamEstimator(instrument).depth_frames(8).tolist() == [0, 7]
    assert StreamEstimator(instrument, options=StreamOptions(online=False)).depth_frames(8).tolist() == [7]
    assert StreamEstimator(instrument, options=StreamOptions(all_depth=True)).depth_frames(8) is None
    assert StreamEstimator(instrument, online=OnlineOptions(shared_frames=0)).depth_frames(8).tolist() == [7]
    assert StreamEstimator(make_backbone("classical"), options=StreamOptions(mode="ttr")).depth_frames(8) is None
