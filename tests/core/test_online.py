"""``vi3_core.online``: the window of clips fitted jointly, its marginal prior, consistency test and restarts, and the
chained odom trajectory (their command-line outputs: tests/cli/test_online_cli.py). Estimator tests use the
ground-truth camera poses of a generated sequence as the "backbone" (up to a scale of 1/3, with 3 mm / 0.1 deg of
noise, like a 3DFM's), so they run in seconds."""

from __future__ import annotations

import math
import re
from dataclasses import replace

import numpy as np
import pytest

from vi3_core.dataset.asl import read_asl
from vi3_core.dataset.generate import cached_sequence
from vi3_core.dataset.sequence import gt_camera_poses, make_clip, sample_clips
from vi3_core.eval.chained import chained_metrics
from vi3_core.fit import ScaleLink
from vi3_core.fit.position import fit_positions
from vi3_core.init import InitOptions, initialise_clip
from vi3_core.init.oracle import oracle_init
from vi3_core.online import OnlineEstimator, OnlineOptions
from vi3_core.online.estimator import scale_agreement, starts_from_own
from vi3_core.online.window import starting_scales
from vi3_core.preintegration import preintegrate
from vi3_core.sim.visual import PoseNoise, noisy_poses
from vi3_core.types import AnchorResult, Geometry, ScaleFit

TRUE_SCALE = 3.0  # metric = 3 x the fake backbone's translation
NOISE = PoseNoise(pos_m=0.003, rot_deg=0.1)


@pytest.fixture(scope="module")
def seq(cache_dir):
    return read_asl(cached_sequence(cache_dir, seconds=10.0, seed=0, with_depth=False))


def _geometry(clip, noise: PoseNoise, rng: np.random.Generator) -> Geometry:
    """GT camera poses in C1 with ``noise``, divided by TRUE_SCALE; flat depth."""
    T = noisy_poses(gt_camera_poses(clip.gt, clip.T_BC), scale=TRUE_SCALE, noise=noise, rng=rng)
    n = clip.n
    return Geometry(T, np.repeat(clip.K[None], n, 0), np.full((n, 4, 4), 1.0), np.ones((n, 4, 4)))


def _run(seq, *, noise: PoseNoise = NOISE, clips=None, options: OnlineOptions | None = None, broken=(),
         init_options: InitOptions | None = None):
    """The estimator over sliding clips: (estimator, online InitResults, the clips' own InitResults, decisions).
    Clips at positions ``broken`` get their poses' x and y axes swapped (a backbone failure)."""
    rng = np.random.default_rng(0)
    est = OnlineEstimator(options=options, init_options=init_options)
    online, own, decisions = [], [], []
    for k, idx in enumerate(clips or sample_clips(len(seq.stamps), n=8, stride=2, mode="sliding")):
        clip = make_clip(seq, idx, with_depth=False, history_s=est.options.online_max_bridge)  # as the node's buffer
        geo = _geometry(clip, noise, rng)
        if k in broken:
            geo = replace(geo, T_wc=geo.T_wc[:, [1, 0, 2, 3]][:, :, [1, 0, 2, 3]])
        own.append(initialise_clip(clip, geo, options=est.init_options))
        init = est.initialise(clip, geo)
        result = AnchorResult(geometry=geo.scaled(init.scale) if init.ok else geo, base=geo, init=init,
                              mode="init" if init.ok else "none", alpha=init.scale, target=init.target)
        est.update(clip, result)
        online.append(init)
        decisions.append(est.last.describe())
    return est, online, own, decisions


def _claims(results) -> tuple[int, np.ndarray, np.ndarray]:
    """(claimed clips, their |scale error|, their relative sigma)."""
    ok = [r for r in results if r.ok]
    return len(ok), np.array([abs(r.scale / TRUE_SCALE - 1) for r in ok]), np.array([r.scale_sigma / r.scale
                                                                                    for r in ok])


def test_position_fit_recovers_the_scale_of_exact_geometry(seq):
    clip = make_clip(seq, sample_clips(len(seq.stamps), mode="sliding")[2], with_depth=False)
    R1 = clip.gt.T_WB[0, :3, :3]
    g, v1 = R1.T @ clip.gt.g_W, R1.T @ clip.gt.v_WB[0]
    pre = preintegrate(clip.imu, clip.stamps, clip.gt.bg, clip.gt.ba)
    geo = _geometry(clip, PoseNoise(), np.random.default_rng(0))
    fit = fit_positions(geo.T_wc, pre, clip.T_BC, g, v1)
    assert abs(fit.scale / TRUE_SCALE - 1) < 0.02 and fit.rms < 0.02
    wrong = fit_positions(geo.T_wc, pre, clip.T_BC, g, v1 + np.array([0.5, 0.0, 0.0]))
    assert wrong.rms > 5 * fit.rms  # a wrong velocity shows in the residual


@pytest.mark.slow
def test_window_earns_scales_the_clips_cannot_claim_alone_and_the_chain_stays_level(seq):
    est, online, own, decisions = _run(seq)
    n_online, err, sig = _claims(online)
    n_own = _claims(own)[0]
    assert n_online > max(n_own, len(online) // 2), (n_online, n_own, decisions)
    assert np.all(err < 3 * sig) and np.all(err < 0.1) and np.median(err) < 0.03, (err, sig)
    assert max(int(d.split()[1]) for d in decisions) >= 5  # the window grows to several clips
    assert any("prior: yes" in d for d in decisions)  # clips older than the window live on as a prior
    traj = est.trajectory
    m = chained_metrics(traj.T_OB, seq.gt.at(traj.stamps).T_WB, stamps=traj.stamps, segment_starts=traj.resets)
    assert len(traj.stamps) == len(np.unique(traj.stamps)) and np.all(np.diff(traj.stamps) > 0)
    assert m.gravity_err_deg < 1.0 and m.drift_pct < 10.0 and len(m.segments) == 1 and not traj.resets, m


@pytest.mark.slow
def test_a_gap_of_dropped_clips_is_bridged_by_the_imu(seq):
    """Clips dropped by a busy worker (a 2 s hole) keep the window: the IMU bridges the gap, no reset."""
    clips = [idx for idx in sample_clips(len(seq.stamps), n=8, stride=2, mode="sliding")
             if not 4.0 <= seq.stamps[idx[0]] - seq.stamps[0] < 6.0]
    est, online, own, decisions = _run(seq, clips=clips)
    assert not any("reset" in d for d in decisions) and not est.trajectory.resets, decisions
    n_online, err, sig = _claims(online)
    assert n_online > _claims(own)[0] and np.all(err < 3 * sig), (n_online, err, sig)


@pytest.mark.slow
def test_overlapping_clips_share_the_window(seq):
    """Clips that overlap (hop < clip span) share frames; the window takes them as they come (at most max_clips)."""
    _, online, _, decisions = _run(seq, clips=sample_clips(len(seq.stamps), n=8, stride=2, mode="sliding", hop=8))
    assert not any("reset" in d for d in decisions) and max(int(d.split()[1]) for d in decisions) == 12
    n_online, err, sig = _claims(online)
    assert n_online >= len(online) // 2 and np.all(err < 3 * sig), (n_online, err, sig)


@pytest.mark.slow
def test_determinism(seq):
    a, b = _run(seq)[0].trajectory, _run(seq)[0].trajectory
    assert np.array_equal(a.stamps, b.stamps) and np.array_equal(a.T_OB, b.T_OB)


@pytest.mark.slow
def test_a_gap_longer_than_the_bridge_restarts_and_starts_a_segment(seq):
    clips = [idx for idx in sample_clips(len(seq.stamps), n=8, stride=2, mode="sliding")
             if not 4.0 <= seq.stamps[idx[0]] - seq.stamps[0] < 6.0]  # 2 s without images
    est, online, _, decisions = _run(seq, clips=clips, options=OnlineOptions(online_max_bridge=1.0))  # forced
    k = next(i for i, d in enumerate(decisions) if "reset: gap" in d)
    assert decisions[k].startswith("window 1 clips"), decisions[k]  # the window restarted from this clip
    assert "prior: yes" in decisions[k]  # the accelerometer bias survived the restart
    assert int(decisions[-1].split()[1]) >= 3  # and the window grew again
    if online[k].ok:
        assert len(est.trajectory.resets) == 1
    n_online, err, sig = _claims(online)
    assert np.all(err < 3 * sig), (err, sig)


@pytest.mark.slow
def test_a_broken_clip_is_rejected_and_named_and_the_window_goes_on(seq):
    baseline = _run(seq)[3]
    k = next(i for i, d in enumerate(baseline) if i >= 4 and int(d.split()[1]) >= 4)
    est, online, _, decisions = _run(seq, broken={k})
    assert online[k].status.value == "rejected", online[k].reason
    assert "backbone failure" in online[k].reason or "inconsistent with the online window" in online[k].reason
    assert decisions[:k] == baseline[:k] and "reset" not in decisions[k + 1]
    assert online[k + 1].ok or online[k + 1].status.value == "unobservable"
    # the rejected clip's status names the window it was tested against: its clips and the seconds they span
    window, span = (float(w) for w in re.match(r"window (\d+) clips over ([\d.]+) s", decisions[k]).groups())
    assert window >= 4 and span >= (window - 1) * 0.5, decisions[k]


def test_oracle_init_without_gt_biases_uses_the_clips_own_gyro_bias(cache_dir):
    """GT tracks without biases (Vicon-only bags): the oracle keeps GT gravity and v1, estimates bg GT-free."""
    # The oracle knows no accelerometer bias when the GT has none: with EuRoC's ~0.1 m/s^2 its scale is ~3 % off, so
    # this test of its gyro-bias path flies a sequence without one.
    seq = read_asl(cached_sequence(cache_dir, seconds=4.0, seed=0, motion="agile", accel_bias=False,
                                   with_depth=False))
    clip = make_clip(seq, sample_clips(len(seq.stamps), mode="sliding")[3], with_depth=False)
    geo = _geometry(clip, PoseNoise(), np.random.default_rng(0))
    no_bias = replace(clip, gt=replace(clip.gt, bg=None, ba=None))
    result = oracle_init(no_bias, geo)
    assert result.ok and abs(result.scale / TRUE_SCALE - 1) < 0.02, result.reason
    assert np.linalg.norm(result.bg - np.asarray(clip.gt.bg).reshape(3)) < 0.005


def test_bad_stream_input_is_named_and_does_not_poison_the_window(seq):
    """A NaN IMU sample rejects its clip only (the window goes on); a clip older than the window restarts it; a clip
    without any IMU is rejected, not a crash."""
    rng = np.random.default_rng(0)
    est = OnlineEstimator()
    idx = sample_clips(len(seq.stamps), n=8, stride=2, mode="sliding")
    decisions = []
    for k in [1, 2, 3, 4, 5, 6, 7, 2]:  # the last clip repeats an old one: out of order
        clip = make_clip(seq, idx[k], with_depth=False)
        if k == 4:
            accel = clip.imu.accel.copy()
            accel[len(accel) // 2] = np.nan
            clip = replace(clip, imu=replace(clip.imu, accel=accel))
        geo = _geometry(clip, NOISE, rng)
        init = est.initialise(clip, geo)
        est.update(clip, AnchorResult(geometry=geo.scaled(init.scale) if init.ok else geo, base=geo, init=init,
                                      mode="init" if init.ok else "none", alpha=init.scale, target=init.target))
        decisions.append((init.status.value, init.reason, est.last.describe()))
    assert decisions[3][0] == "rejected" and "NaN" in decisions[3][1] and "reset" not in decisions[3][2]
    assert "reset" not in decisions[4][2] and int(decisions[4][2].split()[1]) == 4, decisions[4]
    assert "reset: clip out of order" in decisions[-1][2], decisions[-1]
    empty = make_clip(seq, idx[8], with_depth=False)
    empty = replace(empty, imu=empty.imu.select(np.zeros(0, dtype=int)), imu_history=None)
    assert not OnlineEstimator().initialise(empty, _geometry(empty, PoseNoise(), rng)).ok


def test_a_clip_whose_own_scale_disagrees_with_the_window_is_named_by_the_guard():
    """``scale_agreement``: the clip's own 1 / scale against the window's (which holds the clip's evidence and more),
    on the numbers of the real V2_03 clip that carried its window (own 1.55 +- 12 %, window 1.11 +- 2.9 %)."""
    own = ScaleFit(lam=1 / 1.55, scale_rel_sigma=0.122, v1=np.zeros(3), v1_sigma=0.1, g_sigma=0.01, sigma_v=0.003,
                   dof=14.0, variance_factor=1.0, settled=True)
    z, p = scale_agreement(own, 1 / 1.113, 0.029)
    assert z < -3 and p < 1e-3
    z, p = scale_agreement(replace(own, lam=1 / 1.15), 1 / 1.113, 0.029)
    assert abs(z) < 1 and p > 0.3
    assert scale_agreement(own, 1 / 1.2, 0.2) == (0.0, 1.0)  # the window knows no more than the clip: no test


def test_a_clip_whose_own_scale_is_no_better_than_a_guess_is_started_from_its_neighbour():
    """``starts_from_own``: the numbers of a generated flight's clip whose own fit came out at 1/86 of its
    neighbours' scale at a relative sigma of 4630 (from there the window's Gauss-Newton ran off),
    and of the real V2_03 clip above; a scale that is not positive, or has no sigma, is no start either."""
    junk = ScaleFit(lam=0.00283, scale_rel_sigma=4630.0, v1=np.zeros(3), v1_sigma=10.0, g_sigma=0.01, sigma_v=0.003,
                    dof=14.0, variance_factor=1.0, settled=True)
    assert not starts_from_own(junk)
    assert not starts_from_own(replace(junk, scale_rel_sigma=1.0))
    assert starts_from_own(replace(junk, lam=1 / 1.55, scale_rel_sigma=0.122))
    assert not starts_from_own(replace(junk, lam=-1 / 1.55, scale_rel_sigma=0.122))
    assert not starts_from_own(replace(junk, lam=1 / 1.55, scale_rel_sigma=float("nan")))


def test_members_not_sure_of_their_scale_start_from_a_linked_neighbour():
    """``starting_scales``: a member's latest scale where it is positive, else the one before it through their link
    (a ratio of 1 where they have none), the first ones from the first sure one after them; NaN where none is sure.
    The first case is the rendered handheld window whose first clip, started at its own negative least-squares
    scale, took Gauss-Newton off to inverse scales of 1e6 of both signs."""
    link = ScaleLink(log_ratio=0.0435, sigma=0.03)
    np.testing.assert_allclose(starting_scales(np.array([-0.59, 0.933]), [link]), [0.933 / math.exp(0.0435), 0.933])
    nan = float("nan")
    np.testing.assert_allclose(starting_scales(np.array([0.5, nan, -1.0, 0.7]), [link, None, link]),
                               [0.5, 0.5 * math.exp(0.0435), 0.5 * math.exp(0.0435), 0.7])
    np.testing.assert_allclose(starting_scales(np.array([nan, nan, 0.3]), [None, link]),
                               [0.3 / math.exp(0.0435)] * 2 + [0.3])
    assert np.isnan(starting_scales(np.array([nan, -0.2]), [link])).all()
    assert starting_scales(np.array([0.4]), []) == pytest.approx([0.4])


@pytest.mark.slow
def test_a_clip_whose_own_scale_is_negative_still_brings_its_evidence(seq):
    """Issue 36: only the claim is gated, never the evidence. At 1 cm of pose noise some clips' own fits come out
    with a negative scale; they join the window (their IMU and visual constraints count, the window grows by
    them) instead of being dropped with "its own poses carry no scale", and nothing claimed is off."""
    est, online, own, decisions = _run(seq, noise=PoseNoise(pos_m=0.01, rot_deg=0.1))
    negative = [k for k, o in enumerate(own) if "not positive" in o.reason]
    assert negative
    for k in negative:
        assert "carry no scale" not in decisions[k] and "scale: window" in decisions[k], decisions[k]
        assert int(re.match(r"window (\d+) clips", decisions[k]).group(1)) > int(
            re.match(r"window (\d+) clips", decisions[k - 1]).group(1)), (decisions[k - 1], decisions[k])
    n, err, rel = _claims(online)
    assert np.all(err <= 3 * rel)


def test_a_window_of_one_clip_claims_only_what_the_clip_itself_would(seq):
    """The first clip of a stream (or of a restarted window) is fitted alone, with none of its own initialisation's
    checks: where those say no (here every clip's motion is below a raised min_accel_rms), its window does not claim
    it, however small the fit's sigma; the windows of several clips after it claim as before."""
    strict = InitOptions(min_accel_rms=100.0)
    est, online, own, decisions = _run(seq, noise=PoseNoise(pos_m=0.0003, rot_deg=0.01), init_options=strict)
    assert decisions[0].startswith("window 1 clips") and not own[0].ok and "min_accel_rms" in own[0].reason
    assert not online[0].ok and "a window of one clip claims only" in online[0].reason, online[0].reason
    assert online[0].fit.scale_rel_sigma < strict.max_scale_sigma  # the window's sigma alone would have claimed it
    n, err, rel = _claims(online)
    assert n >= len(online) // 2 and np.all(err <= 3 * rel), (n, len(online))


def test_only_a_settled_window_scale_within_odom_max_scale_sigma_goes_into_odom_unclaimed(seq):
    """A clip the claim gate (0.1 %) refuses is chained at the window's scale only where the window fitted it with other
    clips and settled on a positive scale within odom_max_scale_sigma: its poses are the backbone's times that scale.
    The same result is not placed when its fit had not settled, was the clip's alone, or is above the sigma."""
    est, online, _, _ = _run(seq, init_options=InitOptions(max_scale_sigma=0.001))
    assert not any(r.ok for r in online)
    chain, placed = est.chain, [r for r in online if est.chain.places_unclaimed(r)]
    assert len(placed) >= len(online) // 2 and len(chain.trajectory.stamps) > 0
    r = placed[-1]
    assert not chain.places_unclaimed(replace(r, fit=replace(r.fit, settled=False)))
    assert not chain.places_unclaimed(replace(r, fit=replace(r.fit, window_clips=1)))
    assert not chain.places_unclaimed(replace(r, fit=replace(r.fit, scale_rel_sigma=0.11)))
    assert not chain.places_unclaimed(replace(r, fit=replace(r.fit, lam=-r.fit.lam)))
    # the chained positions are metric: the last placed clip's displacement against the truth
    k = max(i for i, x in enumerate(online) if chain.places_unclaimed(x))
    clip = make_clip(seq, sample_clips(len(seq.stamps), n=8, stride=2, mode="sliding")[k], with_depth=False)
    T = chain.state.T_OB
    moved, true = np.linalg.norm(T[-1, :3, 3] - T[0, :3, 3]), np.linalg.norm(clip.gt.T_WB[-1, :3, 3] -
                                                                             clip.gt.T_WB[0, :3, 3])
    assert moved == pytest.approx(true, rel=3 * r.fit.scale_rel_sigma + 0.01)


def test_an_imu_bridge_is_trusted_only_as_far_as_the_accelerometer_bias_walks(seq):
    """Both ends' velocities cancel a constant accelerometer bias from a bridge, not a walking one: its error, the
    integral of b(s) (T / 2 - s) over the bridge, has the variance q^2 T^5 / 120 for a walk of rate q (4000 simulated
    walks agree within 5 %), and a placement's 1-sigma holds exactly that beside the velocities' and the noise's."""
    rng = np.random.default_rng(0)
    T, q, m = 20.0, 0.02, 1000
    ds = T / m
    s = (np.arange(m) + 0.5) * ds
    walks = np.cumsum(rng.normal(scale=q * np.sqrt(ds), size=(4000, m)), axis=1)
    assert np.std(walks @ (T / 2 - s) * ds) == pytest.approx(q * T**2.5 / np.sqrt(120.0), rel=0.05)
    est, online, _, _ = _run(seq)
    chain, init = est.chain, next(r for r in reversed(online) if r.ok)
    t1 = float(chain.state.stamps[-1]) - 1e-3  # bridged from the frame before
    span = t1 - float(chain.state.stamps[-2])
    sigmas = []
    for walk in (0.0, 0.5):
        chain.init_options = replace(est.init_options, accel_bias_walk=walk)
        sigmas.append(chain.placement(t1, init, init.v1, est._imu).sigma)
    assert sigmas[1] ** 2 - sigmas[0] ** 2 == pytest.approx(0.25 * span**5 / 120.0, rel=1e-6)
