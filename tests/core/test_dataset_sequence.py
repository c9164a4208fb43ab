"""ASL folders, ground-truth tracks, clips and the clip sampler; the inertial check on generated sequences."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from vi3_core import so3
from vi3_core.dataset.asl import read_asl
from vi3_core.dataset.generate import EUROC_CAM0, cached_sequence
from vi3_core.dataset.sequence import GroundTruthTrack, make_clip, sample_clips
from vi3_core.errors import CalibrationError, DataError
from vi3_core.preintegration import preintegrate


@pytest.fixture(scope="module")
def generated(cache_dir):
    return cached_sequence(cache_dir, seconds=2.0, seed=0)


def test_generated_asl_layout_and_rates(generated):
    mav0 = generated / "mav0"
    for rel in ("cam0/data.csv", "cam0/sensor.yaml", "imu0/data.csv", "imu0/sensor.yaml", "body.yaml",
                "state_groundtruth_estimate0/data.csv", "depth0/data.csv", "depth0/sensor.yaml"):
        assert (mav0 / rel).is_file(), rel
    seq = read_asl(generated)
    assert len(seq) == 41 and len(list((mav0 / "cam0" / "data").glob("*.png"))) == 41
    assert np.all(np.diff(seq.stamps_ns) == 50_000_000) and np.all(np.diff(seq.imu_ns) == 5_000_000)
    assert np.isin(seq.stamps_ns, seq.imu_ns).all()  # camera stamps on the IMU grid, as in EuRoC
    assert seq.imu_ns[0] < seq.stamps_ns[0] and seq.imu_ns[-1] > seq.stamps_ns[-1]
    np.testing.assert_allclose(seq.calib.T_BC, EUROC_CAM0.T_BC)
    img = seq.image(3)
    assert img.shape == (480, 752) and img.dtype == np.uint8 and img.std() > 20
    depth = seq.gt_depth(3)
    assert depth.dtype == np.float32 and np.isfinite(depth).mean() > 0.99
    # GT velocity is the derivative of GT position (columns in EuRoC's order).
    gt = seq.gt
    fd = np.gradient(gt.T_WB[:, :3, 3], gt.t, axis=0)
    np.testing.assert_allclose(fd[1:-1], gt.v_WB[1:-1], atol=2e-3)
    assert np.abs(gt.bg[0]).max() > 1e-3  # a random initial gyro bias


def test_real_fixture_reads(euroc_fixture):
    seq = read_asl(euroc_fixture.parent)
    assert len(seq) == 5 and seq.image(0).shape == (480, 752)
    assert seq.stamps_ns[0] == 1403636579763555584 and len(seq.imu) == 5
    assert seq.gt is not None and seq.gt_depth(0) is None
    # MH_01's ground truth starts after these frames: a clip gets no GT rather than extrapolated GT.
    clip = make_clip(seq, np.array([0]))  # the fixture's 5 IMU samples (25 ms) cover only the first frame
    assert clip.gt is None and clip.images.shape == (1, 480, 752)
    with pytest.raises(DataError, match="does not cover the clip"):
        make_clip(seq, np.arange(2))
    part = seq.within(seq.stamps[1], seq.stamps[3])  # the span a reference covers
    assert len(part) == 3 and part.stamps_ns[0] == seq.stamps_ns[1] and len(part.imu) == 5
    assert np.array_equal(part.image(2), seq.image(3)) and not np.array_equal(part.image(0), seq.image(0))
    with pytest.raises(DataError, match="no frame of"):
        seq.within(0.0, 1.0)


def _copy(src, dst):
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("*.png"))
    return dst / "mav0"


def test_bad_asl_inputs_name_file_and_problem(generated, tmp_path):
    mav0 = _copy(generated, tmp_path / "a")
    imu_csv = mav0 / "imu0" / "data.csv"
    imu_csv.write_text("#timestamp [ns],gx,gy,gz,ax,ay\n1,0,0,0,0,0\n")
    with pytest.raises(DataError, match="header .* is not EuRoC's: expected 7") as info:
        read_asl(mav0)
    assert str(imu_csv) in str(info.value)
    mav0 = _copy(generated, tmp_path / "b")
    (mav0 / "cam0" / "sensor.yaml").unlink()
    with pytest.raises(CalibrationError, match="sensor.yaml: calibration file does not exist"):
        read_asl(mav0)
    with pytest.raises(DataError, match="not an EuRoC ASL folder"):
        read_asl(tmp_path)
    seq = read_asl(_copy(generated, tmp_path / "c"))
    with pytest.raises(DataError, match=r"\.png: missing or not a readable PNG"):
        seq.image(0)


def test_ground_truth_interpolation():
    t = np.array([0.0, 1.0, 2.0])
    R = so3.exp(np.array([[0, 0, 0.0], [0, 0, 0.4], [0, 0, 0.8]]))
    track = GroundTruthTrack(t, so3.make_T(R, np.array([[0, 0, 0], [1, 0, 0], [1, 2, 0.0]])))
    gt = track.at(np.array([0.5, 1.5]))
    np.testing.assert_allclose(so3.log(gt.T_WB[:, :3, :3])[:, 2], [0.2, 0.6])
    np.testing.assert_allclose(gt.T_WB[:, :3, 3], [[0.5, 0, 0], [1, 1, 0]])
    assert np.isnan(gt.bg).all()  # no biases on a pose-only track
    np.testing.assert_allclose(track.v_WB[1], [0.5, 1.0, 0.0])  # central difference
    with pytest.raises(DataError, match="outside the ground truth"):
        track.at(np.array([2.5]))


def test_sample_clips():
    paper = sample_clips(100, n=8, stride=2)
    assert [c[0] for c in paper] == [0, 42, 85] and all(len(c) == 8 and np.all(np.diff(c) == 2) for c in paper)
    sliding = sample_clips(40, n=4, stride=3, mode="sliding", hop=5)
    assert [c[0] for c in sliding] == [0, 5, 10, 15, 20, 25, 30] and sliding[-1][-1] == 39
    assert [c[0] for c in sample_clips(40, n=4, stride=3, mode="sliding")] == [0, 12, 24]
    assert len(sample_clips(15, n=8, stride=2)) == 1
    with pytest.raises(DataError, match="spans 15 frames; the sequence has 14"):
        sample_clips(14, n=8, stride=2)
    with pytest.raises(ValueError, match="unknown clip sampling mode"):
        sample_clips(40, mode="random")


def test_make_clip(generated):
    seq = read_asl(generated)
    idx = sample_clips(len(seq), n=8, stride=2)[1]
    clip = make_clip(seq, idx)
    und = seq.calib.undistorter()
    assert clip.n == 8 and np.array_equal(clip.images[3], und.apply(seq.image(idx[3])))
    np.testing.assert_allclose(clip.K, und.K)
    assert clip.imu.t[0] < clip.stamps[0] and clip.imu.t[-1] > clip.stamps[-1]
    assert np.sum(clip.imu.t < clip.stamps[0]) == 1 and np.sum(clip.imu.t > clip.stamps[-1]) == 1
    assert clip.imu_history.t[0] < clip.stamps[0] - 0.2
    assert clip.gt.depth.shape == (8, 480, 752) and clip.gt.T_WB.shape == (8, 4, 4)
    np.testing.assert_allclose(clip.gt.T_WB, seq.gt.T_WB[np.searchsorted(seq.gt.t_ns, seq.stamps_ns[idx])])
    assert make_clip(seq, idx, with_depth=False).gt.depth is None
    with pytest.raises(DataError, match="out of range"):
        make_clip(seq, np.array([0, 41]))


@pytest.mark.slow
def test_inertia_agrees_noise_free_preintegration_reproduces_gt(cache_dir):
    """Preintegrating the noise-free IMU with GT biases and gravity gives GT relative poses over 0.8 s."""
    seq = read_asl(cached_sequence(cache_dir, seconds=2.0, seed=5, imu_noise=False, with_depth=False))
    for start in (0, 12, 24):
        clip = make_clip(seq, np.arange(start, start + 17))  # 16 intervals at 20 Hz = 0.8 s
        gt = clip.gt
        R_W1 = gt.T_WB[0, :3, :3]
        pre = preintegrate(clip.imu, clip.stamps, bg=gt.bg, ba=gt.ba)
        states = pre.propagate(g=R_W1.T @ gt.g_W, v1=R_W1.T @ gt.v_WB[0])
        T_rel = so3.relative_to_first(gt.T_WB)
        assert np.linalg.norm(states.p - T_rel[:, :3, 3], axis=1).max() < 1e-3
        assert np.degrees(so3.angle(np.swapaxes(states.R, 1, 2) @ T_rel[:, :3, :3])).max() < 0.05
        assert np.linalg.norm(T_rel[-1, :3, 3]) > 0.1  # the drone actually moved
        # A wrong gyro bias breaks it (the check can fail).
        wrong = preintegrate(clip.imu, clip.stamps, bg=gt.bg + 0.01, ba=gt.ba)
        assert np.degrees(so3.angle(np.swapaxes(wrong.R, 1, 2) @ T_rel[:, :3, :3])).max() > 0.3
