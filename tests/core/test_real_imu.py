"""Scale claims on a real IMU: EuRoC V1_02_medium's IMU and ground truth (``../shared``), with the ground-truth
camera poses at an arbitrary scale and 3 mm / 0.1 deg of noise per frame standing in for a 3DFM (the evaluation's
``gt`` pose instrument). The acceptance of the error model: every claimed scale supported by its sigma."""

from __future__ import annotations

import json

import numpy as np
import pytest

from vi3_core import so3
from vi3_core.backbones.ground_truth import GroundTruthPoses
from vi3_core.dataset.sequence import make_clip
from vi3_core.eval.runner import EvalOptions, clip_indices, evaluate_clip
from vi3_core.fit import metric_fit
from vi3_core.fit.noise import ImuNoiseModel
from vi3_core.init import InitOptions, initialise_clip
from vi3_core.online import StreamEstimator
from vi3_core.preintegration import preintegrate
from vi3_core.sim.visual import PoseNoise
from vi3_ros import cli


def test_no_folder_images_but_camera_stamps_on_the_imu_clock(v102):
    assert not v102.has_images and len(v102) > 700
    np.testing.assert_allclose(np.diff(v102.stamps), 0.05, atol=1e-6)
    assert np.isin(v102.stamps_ns, v102.imu_ns).all()
    with pytest.raises(Exception, match="--backbone gt"):
        v102.image(0)


def _chained(seq, noise: PoseNoise, *, seed: int = 0, max_clips: int | None = None, init: InitOptions | None = None):
    """The sliding clips of ``seq`` (each sharing its first frame with the one before) through the pose instrument
    and the stream estimator, as ``vi3 eval`` runs them: yields (clip, the instrument's base geometry, its true metres
    per model unit, the window's InitResult)."""
    instrument = GroundTruthPoses(noise=noise, seed=seed)
    stream = StreamEstimator(instrument, init=init)
    for idx in clip_indices(len(seq), options=EvalOptions(clips="sliding"), chained=True)[:max_clips]:
        clip = make_clip(seq, idx, history_s=stream.online_options.online_max_bridge, with_images=False)
        out = stream.process(clip)
        yield clip, out.result.base, instrument.last_scale, out.init


def test_the_evaluation_knows_the_instruments_exact_scale(v102):
    """``ClipEval.exact_scale`` is the metres per model unit the instrument predicted the clip at."""
    instrument = GroundTruthPoses(noise=PoseNoise(pos_m=0.003, rot_deg=0.1))
    assert instrument.exact_scale is None
    idx = clip_indices(len(v102), options=EvalOptions(clips="sliding"), chained=True)[10]
    ev = evaluate_clip(make_clip(v102, idx, with_images=False), EvalOptions().stream(instrument, online=False))
    assert ev.exact_scale == instrument.last_scale > 0
    np.testing.assert_allclose(ev.columns["base"].scale_fit * ev.exact_scale, 1.0, atol=0.05)


@pytest.mark.slow
def test_real_imu_claims_are_supported_by_their_sigma(v102):
    """Chained and independent: no claimed clip more than 10 % off or beyond 3 sigma; the window claims most clips
    once the drone flies, the clips on their own few (3 mm of noise hides the scale of one 0.7 s clip)."""
    chained, own = [], []
    for clip, base, truth, init in _chained(v102, PoseNoise(pos_m=0.003, rot_deg=0.1)):
        free = initialise_clip(clip, base)
        for results, r in ((own, free), (chained, init)):
            results.append((r.ok, abs(r.scale / truth - 1.0), r.scale_sigma / r.scale))
    for name, results in (("chained", chained), ("independent", own)):
        claimed = [(e, s) for ok, e, s in results if ok]
        assert all(e < 0.1 and e < 3 * s for e, s in claimed), (name, claimed)
    assert np.mean([ok for ok, _, _ in chained[14:]]) > 0.6, chained  # the first 10 s: a slow take-off
    assert np.median([e for ok, e, _ in chained if ok]) < 0.04


def test_gt_seed_makes_the_instrument_noise_repeatable_and_distinct(shared_dir, tmp_path, capsys):
    """``vi3 eval --backbone gt --gt-seed N``: the same seed gives the same report, another seed other noise."""
    path = shared_dir / "data" / "euroc_v102_imu_gt"
    if not path.is_dir():
        pytest.skip(f"real EuRoC IMU data missing at {path}")

    def base_errors(seed: int, name: str) -> list:
        out = tmp_path / f"{name}.json"
        assert cli.main(["eval", str(path), "--backbone", "gt", "--gt-noise", "0.003,0.1", "--gt-seed", str(seed),
                         "--independent", "--max-clips", "2", "--no-progress", "--json-out", str(out)]) == 0
        return json.loads(out.read_text())["base_all"]["rot_deg"]  # over every clip, claimed or not

    assert base_errors(1, "a") == base_errors(1, "b") != base_errors(2, "c")
    assert cli.main(["eval", str(path), "--gt-seed", "1", "--no-progress"]) == 2
    assert "--gt-seed need --backbone gt" in capsys.readouterr().err
    # issue 39: depth noise on an input without depth ground truth was ignored without a word (exit 0)
    assert cli.main(["eval", str(path), "--backbone", "gt", "--gt-depth-noise", "0.1", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--gt-depth-noise needs depth ground truth" in err, err


@pytest.mark.slow
def test_the_window_does_not_amplify_round_off(v102):
    """A 1e-13 relative change of the accelerometer samples (round-off of another BLAS or CPU) leaves every status
    and moves no scale by more than 1 %: the window's prior once dropped weak directions at a cut-off, and this change
    of the real V1_02 IMU at 1 mm / 0.05 deg (noise seed 1) then cascaded into confident wrong scales."""
    import dataclasses

    rng = np.random.default_rng(5)
    accel = v102.imu.accel * (1 + 1e-13 * rng.standard_normal(v102.imu.accel.shape))
    bumped = dataclasses.replace(v102.imu, accel=accel)
    runs = [[(init.status, init.scale) for *_, init in _chained(dataclasses.replace(v102, imu=imu),
                                                                  PoseNoise(pos_m=0.001, rot_deg=0.05), seed=1,
                                                                  max_clips=20)]
            for imu in (v102.imu, bumped)]
    assert [s for s, _ in runs[0]] == [s for s, _ in runs[1]]
    assert sum(s.value == "ok" for s, _ in runs[0]) >= 10
    assert all(abs(a / b - 1) < 0.01 for (_, a), (_, b) in zip(*runs) if np.isfinite(a) and np.isfinite(b))


def test_the_accelerometer_matrix_undoes_an_accelerometer_read_through_it(v102):
    """The real V1_02 accelerometer read through a matrix of 1-2 % scale factors and 2-5 % cross-axis terms (an
    uncalibrated consumer IMU's): with that matrix as ``accel_matrix`` the window's statuses and scales are those of
    the IMU as recorded (to round-off); without it they are not."""
    import dataclasses

    A = np.array([[1.02, 0.04, 0.0], [-0.05, 0.99, 0.03], [0.0, 0.02, 1.01]])
    read = dataclasses.replace(v102, imu=v102.imu.read_through(np.linalg.inv(A)))
    matrix = InitOptions(accel_matrix=" ".join(repr(float(x)) for x in A.ravel()))
    runs = [[(init.status, init.scale) for *_, init in _chained(seq, PoseNoise(pos_m=0.001, rot_deg=0.05), seed=1,
                                                                  max_clips=20, init=options)]
            for seq, options in ((v102, None), (read, matrix), (read, None))]
    assert [s for s, _ in runs[0]] == [s for s, _ in runs[1]] and sum(s.value == "ok" for s, _ in runs[0]) >= 10
    assert all(abs(a / b - 1) < 1e-6 for (_, a), (_, b) in zip(runs[0], runs[1]) if np.isfinite(a) and np.isfinite(b))
    assert max(abs(a / b - 1) for (_, a), (_, b) in zip(runs[0], runs[2]) if np.isfinite(a) and np.isfinite(b)) > 0.01
    with pytest.raises(ValueError, match="accel_matrix must be 9 numbers"):
        InitOptions(accel_matrix="1 0 0 0 1 0")
    with pytest.raises(ValueError, match="is no accelerometer calibration"):
        InitOptions(accel_matrix="1 0 0 0 1 0 0 0 nan")


@pytest.mark.slow
def test_aggressive_flight_claims_no_confident_wrong_scale(v203):
    """Issue 37: on the real V2_03 flight at 3 mm / 0.1 deg (noise seed 0) the window claimed 1.11 and 1.13 at 2.9 and
    3.4 % (35.0 and 39.9 s into the flight; 3.9 and 3.8 sigma): the clip at 35.0 s on its own said 1.55 +- 12 % and
    carried the window, and the window took the gyro's integrated attitude between its clips as exact (it drifts
    0.3-1.7 deg over 8 s of this flight's turns). The 30 s around them: none more than 10 % off, every claim within 3.5
    sigma (39.9 s is the worst, 3.05 sigma: a systematic error of the real IMU there, docs/accuracy.md), and the clip
    whose own scale disagrees with the window's is refused by the guard."""
    t0 = float(v203.stamps[0])
    claims, refused = [], []
    for clip, _, truth, init in _chained(v203, PoseNoise(pos_m=0.003, rot_deg=0.1), seed=0, max_clips=65):
        if clip.stamps[0] - t0 < 16.0:
            continue
        if init.ok:
            claims.append((float(clip.stamps[0] - t0), init.scale / truth - 1.0, init.scale_sigma / init.scale))
        elif "own scale is" in init.reason:
            refused.append(float(clip.stamps[0] - t0))
    assert len(claims) >= 25, claims
    assert all(abs(e) < 0.1 and abs(e) < 3.5 * s for _, e, s in claims), [c for c in claims if abs(c[1]) > 3 * c[2]]
    assert any(abs(t - 35.0) < 0.1 for t in refused), refused


def _takeoff_claims(v203) -> list[tuple[float, float, float, str]]:
    """(s into the flight, error, relative sigma, reason) of V2_03's first 17 clips through the window (3 mm / 0.1
    deg, noise seed 0); the error and sigma NaN where a clip is not claimed."""
    t0 = float(v203.stamps[0])
    return [(float(clip.stamps[0] - t0), init.scale / truth - 1.0 if init.ok else np.nan,
             init.scale_sigma / init.scale if init.ok else np.nan, init.reason)
            for clip, _, truth, init in _chained(v203, PoseNoise(pos_m=0.003, rot_deg=0.1), seed=0, max_clips=17)]


@pytest.fixture(scope="module")
def takeoff_claims(v203) -> list[tuple[float, float, float, str]]:
    """``_takeoff_claims`` at the shipped ``SETTLED_SIGMAS``, for both tests below."""
    return _takeoff_claims(v203)


def test_a_member_the_window_cannot_fix_does_not_hold_up_the_newest_clips_claim(takeoff_claims):
    """On the real V2_03 flight's take-off the window holds clips from before it whose scale it cannot fix: one's lam
    swings from step to step (from 19 to 430, through zero), so the fit never meets its tolerance, which is relative
    to each lam. The newest clip's scale moves by a few hundredths of its sigma there: it has settled
    (``FitResult.settled``) and is claimed, right."""
    claims = [(t, e, s) for t, e, s, _ in takeoff_claims if np.isfinite(e)]
    assert len(claims) >= 4 and claims[0][0] < 8.0, claims
    assert all(abs(e) < 0.1 and abs(e) < 3 * s for _, e, s in claims), claims


def test_a_clip_whose_fit_has_not_settled_is_not_claimed_and_says_why(v203, takeoff_claims, monkeypatch):
    """The same take-off where no step still to go is small enough (``SETTLED_SIGMAS`` 0): no clip is claimed, and
    each one claimed above names the window's step."""
    claimed = [t for t, e, _, _ in takeoff_claims if np.isfinite(e)]
    monkeypatch.setattr(metric_fit, "SETTLED_SIGMAS", 0.0)
    refused = _takeoff_claims(v203)
    assert not any(np.isfinite(e) for _, e, _, _ in refused)
    why = {t: reason for t, _, _, reason in refused}
    assert claimed and all("has not settled" in why[t] and "step still to go" in why[t] for t in claimed), \
        [why[t] for t in claimed]


@pytest.mark.parametrize("name", ["v102", "v203"])
def test_gyro_scale_error_covers_the_real_imus_attitude(name, request):
    """``gyro_scale_error`` against the real EuRoC gyro: integrated with its ground-truth bias over 8.4 s (an online
    window) from every 2 s of the flight, its attitude errs by 0.16 % (V1_02) / 0.25 % (V2_03) of the angle turned
    (medians), under the model's 0.5 %, and at no window by more than twice the model's."""
    seq = request.getfixturevalue(name)
    gt, imu = seq.gt, seq.imu
    start, end = max(gt.t[0], imu.t[0]) + 1.0, min(gt.t[-1], imu.t[-1]) - 10.0
    share = []
    for t0 in np.arange(start, end, 2.0):
        stamps = np.linspace(t0, t0 + 8.4, 13)
        truth = gt.at(stamps)
        pre = preintegrate(imu.window(stamps[0], stamps[-1]), stamps, truth.bg)
        R_rel = truth.T_WB[0, :3, :3].T @ truth.T_WB[:, :3, :3]
        err = so3.angle(np.swapaxes(R_rel, 1, 2) @ pre.R).max()
        inside = (imu.t >= stamps[0]) & (imu.t <= stamps[-1])
        turned = np.linalg.norm(imu.gyro[inside], axis=1).sum() * np.median(np.diff(imu.t))
        share.append(err / turned)
    model = ImuNoiseModel().gyro_scale_error
    assert len(share) > 10 and np.median(share) < 0.6 * model and np.max(share) < 2 * model, np.median(share)
