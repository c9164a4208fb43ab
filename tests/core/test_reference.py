"""The batch reference fit (``vi3_core.eval.reference``), ``vi3 reference`` and ``vi3 eval --reference``, on the real
V1_02 IMU with its ground truth standing in for an offline reconstruction: moved into another world, shrunk to its
own units, its stamps on a camera clock 30 ms late, with position noise."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vi3_core import so3
from vi3_core.errors import DataError
from vi3_core.eval.reference import fit_halves, fit_reference
from vi3_core.eval.tum import read_tum, write_tum
from vi3_core.fit.noise import ImuNoiseModel
from vi3_core.init import InitOptions
from vi3_ros import cli

SCALE = 0.25  # metres per reconstruction unit
OFFSET = 0.030  # s, camera stamp minus IMU stamp
R0 = Rotation.from_rotvec([0.4, -1.1, 2.0]).as_matrix()  # the reconstruction's world against the gravity-aligned one


def _reconstruction(seq, *, step: int = 2, pos_m: float = 0.003, seed: int = 0):
    """(camera-clock stamps [n], camera-to-world poses [n,4,4] in the reconstruction's units and world)."""
    t = seq.stamps[::step]
    T_WC = seq.gt.at(t).T_WB @ seq.calib.T_BC
    T = T_WC.copy()
    T[:, :3, :3] = R0 @ T_WC[:, :3, :3]
    noise = np.random.default_rng(seed).normal(0.0, pos_m, (len(t), 3))
    T[:, :3, 3] = ((T_WC[:, :3, 3] + noise) @ R0.T + [3.0, -1.0, 0.5]) / SCALE
    return t + OFFSET, T


@pytest.fixture(scope="module")
def fitted(v102):
    stamps, T = _reconstruction(v102)
    fit = fit_reference(stamps, T, v102.imu, v102.calib.T_BC)
    return stamps, T, fit


def test_the_fit_recovers_scale_gravity_and_time_offset(v102, fitted):
    stamps, T, fit = fitted
    assert abs(fit.scale / SCALE - 1.0) < 0.015 and 5e-4 < fit.rel_sigma < 0.015
    assert abs(fit.scale / SCALE - 1.0) < 4 * fit.rel_sigma  # the real IMU keeps ~0.8 % the model does not see
    assert fit.time_offset == pytest.approx(OFFSET, abs=0.003)
    g_true = R0 @ v102.gt.g_W
    assert np.degrees(np.arccos(g_true @ fit.g / np.linalg.norm(g_true) / np.linalg.norm(fit.g))) < 1.0
    assert 0.001 < fit.sigma_ref < 0.006 and fit.keyframes > 0.9 * len(stamps)


def test_the_weighting_is_the_datas_not_the_assumed_noise(v102, fitted):
    """The IMU's, the bias walk's and the centres' variances are estimated: starting from accelerometer noise densities
    a decade apart, the fits meet (with assumed weights the scale moved by 0.8 % here and by a quarter on a gentle
    handheld recording)."""
    stamps, T, fit = fitted
    fits = [fit_reference(stamps, T, v102.imu, v102.calib.T_BC, time_offset=fit.time_offset,
                          noise=ImuNoiseModel(accel_noise_density=q)) for q in (0.006, 0.06)]
    assert abs(fits[0].scale / fits[1].scale - 1.0) < 0.001
    assert fits[0].imu_noise_factor * 0.006 == pytest.approx(fits[1].imu_noise_factor * 0.06, rel=0.05)
    assert fits[0].chi2_dof == pytest.approx(1.0, abs=0.05) and fits[1].chi2_dof == pytest.approx(1.0, abs=0.05)


def test_a_drifting_accelerometer_bias_is_followed(v102):
    """A bias that ramps by 0.2 m/s^2 over the record (a consumer IMU warming up) is a walk the fit finds, and the
    scale stays right; noise-free centres (a reconstruction better than the IMU can tell) keep a finite weight."""
    stamps, T = _reconstruction(v102, pos_m=0.0)
    t = v102.imu.t
    ramp = 0.2 * ((t - t[0]) / (t[-1] - t[0]))[:, None] * np.array([0.6, -0.8, 0.0])
    imu = dataclasses.replace(v102.imu, accel=v102.imu.accel + ramp)
    fit = fit_reference(stamps, T, imu, v102.calib.T_BC, time_offset=OFFSET)
    assert abs(fit.scale / SCALE - 1.0) < 0.015 and abs(fit.scale / SCALE - 1.0) < 4 * fit.rel_sigma
    assert fit.ba_spread > 0.05 and fit.accel_bias_walk > 0.003
    assert np.isfinite(fit.sigma_ref) and fit.sigma_ref < 1e-3


def test_the_accelerometer_matrix_is_recovered(v102, fitted):
    """An accelerometer read through a known matrix (scale factors of 1-2 %, cross-axis terms of 2-5 %, as an
    uncalibrated consumer IMU's): the fit with ``accel_intrinsics`` finds that matrix times what it finds for the real
    IMU itself, and the same scale."""
    stamps, T, fit = fitted
    A = np.array([[1.02, 0.04, 0.0], [-0.05, 0.99, 0.03], [0.0, 0.02, 1.01]])
    imu = dataclasses.replace(v102.imu, accel=v102.imu.accel @ np.linalg.inv(A).T)
    own, read = (fit_reference(stamps, T, i, v102.calib.T_BC, time_offset=fit.time_offset, accel_intrinsics=True)
                 for i in (v102.imu, imu))
    np.testing.assert_allclose(read.accel_matrix, A @ own.accel_matrix, atol=0.01)
    assert abs(read.scale / own.scale - 1.0) < 0.005 and abs(own.scale / SCALE - 1.0) < 4 * own.rel_sigma
    assert 0.0 < own.accel_matrix_sigma.max() < 0.05 and np.all(fit.accel_matrix == np.eye(3))


def test_the_halves_agree_within_their_sigmas(v102, fitted):
    stamps, T, fit = fitted
    a, b = fit_halves(stamps, T, v102.imu, v102.calib.T_BC, time_offset=fit.time_offset)
    assert a.span[1] < b.span[0] and a.keyframes + b.keyframes == fit.keyframes
    assert abs(a.scale - b.scale) < 3 * np.hypot(a.scale_sigma, b.scale_sigma)
    assert a.rel_sigma > fit.rel_sigma and b.rel_sigma > fit.rel_sigma


def test_the_body_track_is_metric_and_gravity_aligned(v102, fitted):
    stamps, T, fit = fitted
    T_WB = fit.body_track(stamps, T, v102.calib.T_BC)
    gt = v102.gt.at(stamps - OFFSET).T_WB
    np.testing.assert_allclose(T_WB[0, :3, 3], 0.0, atol=1e-12)
    np.testing.assert_allclose(so3.nearest_rotation(T_WB[:, :3, :3]), T_WB[:, :3, :3], atol=1e-9)
    # gravity-aligned: each body's tilt (its z axis against the world's) as the ground truth's, to a degree
    np.testing.assert_allclose(T_WB[:, 2, :3], gt[:, 2, :3], atol=0.02)
    path, path_gt = (np.linalg.norm(p[:, :3, 3] - p[0, :3, 3], axis=1) for p in (T_WB, gt))
    assert np.max(np.abs(path - path_gt)) < 0.015 * np.max(path_gt) + 0.01


def test_a_reconstruction_the_imu_does_not_cover_is_refused(v102, fitted):
    stamps, T, _ = fitted
    with pytest.raises(DataError, match="the IMU covers 0 of"):
        fit_reference(stamps + 1000.0, T, v102.imu, v102.calib.T_BC, time_offset=0.0)
    with pytest.raises(DataError, match="stamps must increase"):
        fit_reference(stamps[::-1], T, v102.imu, v102.calib.T_BC)
    with pytest.raises(DataError, match=">= 10 finite poses"):
        fit_reference(stamps[:5], T[:5], v102.imu, v102.calib.T_BC)


@pytest.mark.slow
def test_reference_then_eval_scores_a_recording_against_it(euroc_v102, v102, tmp_path, capsys):
    """``vi3 reference`` writes a metric TUM file; ``vi3 eval --reference`` scores the recording against it as
    against its own ground truth (about the same claims and drift). The reconstruction is posed at every frame: a
    reference at 5 Hz, interpolated to the 20 Hz frames, misplaces the drone by centimetres and claims 1 clip of 24
    where its own ground truth claims 6."""
    stamps, T = _reconstruction(v102, step=1, pos_m=0.001)
    poses, out = tmp_path / "recon.tum", tmp_path / "ref.tum"
    write_tum(poses, stamps, T)
    assert cli.main(["reference", str(euroc_v102), "--poses", str(poses), "-o", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert abs(report["scale"] / SCALE - 1.0) < 0.02 and abs(report["halves_z"]) < 3
    t_ref, T_ref = read_tum(out)
    assert len(t_ref) == report["keyframes"] and np.all(np.diff(t_ref) > 0)
    assert cli.main(["reference", str(euroc_v102), "--poses", str(poses), "-o", str(out)]) == 2
    assert "exists; pass --force" in capsys.readouterr().err
    assert cli.main(["reference", str(euroc_v102), "--poses", str(poses), "-o", str(out), "--force",
                     "--accel-intrinsics"]) == 0
    text = capsys.readouterr().out
    assert "accelerometer matrix (specific force = A x reading, rows) [+" in text and "halves:" in text
    matrix = text.split('--param accel_matrix="')[1].split('"')[0]
    assert InitOptions(accel_matrix=matrix).accel_A is not None  # what it prints, the node takes

    runs = {}
    for name, extra in (("own", []), ("reference", ["--reference", str(out)])):
        args = ["eval", str(euroc_v102), "--backbone", "gt", "--gt-noise", "0.003,0.1", "--clips", "sliding",
                "--max-clips", "24", "--json", *extra]
        assert cli.main(args) == 0
        runs[name] = json.loads(capsys.readouterr().out)
    own, ref = runs["own"], runs["reference"]
    assert ref["n_clips"] == own["n_clips"] == 24 and ref["chained"]["applicable"]
    assert ref["claimed_outliers"]["count"] == 0 and abs(ref["n_ok"] - own["n_ok"]) <= 3
    assert abs(ref["chained"]["drift_pct"] - own["chained"]["drift_pct"]) < 1.0


def test_eval_reference_refuses_what_it_cannot_use(euroc_v102, tmp_path, capsys):
    bad = tmp_path / "bad.tum"
    bad.write_text("0 0 0 0 0 0 0 1\n")
    args = ["eval", str(euroc_v102), "--backbone", "gt", "--max-clips", "1"]
    assert cli.main([*args, "--reference", str(bad)]) == 2
    assert "a reference needs >= 2 poses" in capsys.readouterr().err
    assert cli.main(["eval", str(euroc_v102), *args[1:], "--reference", str(bad)]) == 2
    assert "--reference is the ground truth of one input" in capsys.readouterr().err
