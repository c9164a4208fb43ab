"""``vi3 make-bag --from-euroc`` on the layouts real EuRoC recordings have, each cut from the real V1_02 CSVs (a few
seconds, cam0 at a quarter of its resolution): ground truth that starts before, at or after the IMU (by 5 ms, 2.8 us
off the IMU's clock, 0.5 s), at its own rate (V1_02's 40 Hz on the IMU's ns grid; 200 Hz on it with a jittering IMU
clock, as in the machine-hall sequences), and with a gap. The written GT covers every rendered frame, no frame is
rendered in a GT gap, and ``vi3 eval`` scores every clip."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from euroc_cuts import quarter_cam0

from vi3_core.dataset.asl import read_asl, read_groundtruth, read_imu
from vi3_core.dataset.generate import MAX_GT_GAP_NS
from vi3_core.eval.runner import EvalOptions, clip_indices
from vi3_ros import cli

pytestmark = pytest.mark.slow  # every test here renders and evaluates a cut of a real recording

MS = 1_000_000  # ns
START_NS = 10_000 * MS  # the cut starts 10 s into V1_02's GT: the drone is flying
IMU_NS = 2_500 * MS  # IMU length of a cut


def _cut(src: Path, dst: Path, *, gt_before_ns: int, gt_after_ns: int, gt_shift_ns: int = 0, gt_hz: float | None = None,
         imu_jitter_ns: int = 0, drop_gt_ns: tuple[int, int] | None = None) -> Path:
    """A ``mav0`` folder cut from the recording ``src``: IMU_NS of its IMU from START_NS after its GT's first row
    (stamps moved by up to ``imu_jitter_ns``, as the real IMU clock jitters); its GT rows moved by ``gt_shift_ns``
    (or resampled at ``gt_hz`` onto stamps off the IMU's grid), from ``gt_before_ns`` before the IMU's first sample
    to ``gt_after_ns`` after its last (negative: inside), without the rows in ``drop_gt_ns`` (ns after the IMU's
    first sample, open interval); cam0 at 188 x 120."""
    dst.mkdir(parents=True)
    for rel in ("imu0", "state_groundtruth_estimate0", "cam0"):
        (dst / rel).mkdir()
        (dst / rel / "sensor.yaml").write_bytes((src / rel / "sensor.yaml").read_bytes())
    (dst / "body.yaml").write_bytes((src / "body.yaml").read_bytes())
    (dst / "cam0" / "sensor.yaml").write_text(quarter_cam0((dst / "cam0" / "sensor.yaml").read_text()))
    imu_lines = (src / "imu0" / "data.csv").read_text().splitlines()
    gt_lines = (src / "state_groundtruth_estimate0" / "data.csv").read_text().splitlines()
    imu_ns = np.array([int(r.split(",")[0]) for r in imu_lines[1:]])
    gt_ns = np.array([int(r.split(",")[0]) for r in gt_lines[1:]])
    t0 = gt_ns[0] + START_NS
    keep = (imu_ns >= t0) & (imu_ns <= t0 + IMU_NS)
    jitter = np.random.default_rng(0).integers(-imu_jitter_ns, imu_jitter_ns + 1, size=keep.sum())
    imu_rows = [f"{ns + j}{r[r.index(','):]}" for ns, j, r in zip(imu_ns[keep], jitter, np.array(imu_lines[1:])[keep])]
    (dst / "imu0" / "data.csv").write_text("\n".join([imu_lines[0], *imu_rows]) + "\n")
    if gt_hz is None:
        gt_out = gt_ns + gt_shift_ns
        rows = [f"{ns}{r[r.index(','):]}" for ns, r in zip(gt_out, gt_lines[1:])]
    else:  # linear in every column, the quaternion renormalised: smooth enough 5 ms apart
        values = np.loadtxt(src / "state_groundtruth_estimate0" / "data.csv", delimiter=",", skiprows=1)[:, 1:]
        gt_out = np.arange(gt_ns[0], gt_ns[-1], int(1e9 / gt_hz)) + gt_shift_ns
        cols = np.stack([np.interp(gt_out, gt_ns, values[:, k]) for k in range(values.shape[1])], 1)
        cols[:, 3:7] /= np.linalg.norm(cols[:, 3:7], axis=1, keepdims=True)
        rows = [f"{ns}," + ",".join(f"{x:.6f}" for x in c) for ns, c in zip(gt_out, cols)]
    lo, hi = t0 - gt_before_ns, t0 + IMU_NS + gt_after_ns
    inside = (gt_out >= lo) & (gt_out <= hi)
    if drop_gt_ns is not None:
        inside &= ~((gt_out > t0 + drop_gt_ns[0]) & (gt_out < t0 + drop_gt_ns[1]))
    (dst / "state_groundtruth_estimate0" / "data.csv").write_text(
        "\n".join([gt_lines[0], *np.array(rows)[inside]]) + "\n")
    return dst


def _make_bag(recording: Path, out: Path, capsys) -> str:
    """``vi3 make-bag out --from-euroc recording --no-depth``; returns its stderr."""
    code = cli.main(["make-bag", str(out), "--from-euroc", str(recording), "--no-depth"])
    stdout, stderr = capsys.readouterr()
    assert code == 0 and stdout.startswith("wrote "), stderr
    return stderr


def _assert_eval_scores_every_clip(asl: Path, n_frames: int, capsys) -> None:
    """``vi3 eval asl`` (chained, sliding clips, the embedded backbone) evaluates every clip of the sequence."""
    code = cli.main(["eval", str(asl), "--json", "--no-progress"])
    stdout, stderr = capsys.readouterr()
    report = json.loads(stdout)
    assert code == 0 and "partial" not in report, stderr
    assert report["n_clips"] == len(clip_indices(n_frames, options=EvalOptions(clips="sliding"), chained=True)) >= 2


LAYOUTS = {  # name: _cut's options
    "gt 5 ms before the IMU, 25 ms after": dict(gt_before_ns=5 * MS, gt_after_ns=25 * MS, gt_shift_ns=-5 * MS),
    "gt 2.8 us before the IMU, off its clock": dict(gt_before_ns=2_800, gt_after_ns=0, gt_shift_ns=-2_800),
    "gt at the IMU": dict(gt_before_ns=0, gt_after_ns=0),
    "gt 0.5 s after the IMU, ending 0.3 s before": dict(gt_before_ns=-500 * MS, gt_after_ns=-300 * MS),
    "machine hall: 200 Hz gt, the IMU clock jittering about it": dict(gt_before_ns=-300 * MS, gt_after_ns=0,
                                                                       gt_hz=200.0, imu_jitter_ns=400),
}


@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_the_written_gt_covers_every_frame_and_eval_scores_every_clip(euroc_v102, tmp_path, capsys, layout):
    recording = _cut(euroc_v102, tmp_path / "rec" / "mav0", **LAYOUTS[layout])
    assert _make_bag(recording, tmp_path / "out", capsys) == ""
    seq = read_asl(tmp_path / "out" / "asl")
    src_imu_ns, _ = read_imu(recording)
    src_gt = read_groundtruth(recording)
    # Frames at 20 Hz on the IMU's own stamps over the whole span IMU and GT share (jitter aside).
    lo, hi = max(src_imu_ns[0], src_gt.t_ns[0]), min(src_imu_ns[-1], src_gt.t_ns[-1])
    assert np.isin(seq.stamps_ns, src_imu_ns).all() and seq.stamps_ns[0] == src_imu_ns[src_imu_ns >= lo][0]
    assert np.abs(np.diff(seq.stamps_ns) - 50 * MS).max() <= 1_000 and hi - seq.stamps_ns[-1] <= 50 * MS + 1_000
    # GT: the recording's rows, bit for bit, over the IMU kept and bracketing every frame.
    rows = np.searchsorted(src_gt.t_ns, seq.gt.t_ns)
    assert np.array_equal(src_gt.t_ns[rows], seq.gt.t_ns) and np.all(np.diff(rows) == 1)
    assert np.array_equal(seq.gt.v_WB, src_gt.v_WB[rows]) and np.array_equal(seq.gt.ba, src_gt.ba[rows])
    assert seq.gt.t_ns[0] <= seq.stamps_ns[0] and seq.gt.t_ns[-1] >= seq.stamps_ns[-1]
    assert seq.gt.t_ns[0] <= seq.imu_ns[0] or seq.gt.t_ns[0] == src_gt.t_ns[0]
    _assert_eval_scores_every_clip(tmp_path / "out" / "asl", len(seq), capsys)


def test_no_frame_is_rendered_in_a_gt_gap_and_the_gap_is_named(euroc_v102, tmp_path, capsys):
    """A GT gap of 0.625 s leaves a hole in the frames, named on stderr; one missing 40 Hz row (50 ms) is no gap."""
    recording = _cut(euroc_v102, tmp_path / "rec" / "mav0", gt_before_ns=0, gt_after_ns=0,
                     drop_gt_ns=(1_000 * MS, 1_625 * MS))
    imu_ns = read_imu(recording)[0]
    t0, missing_row = imu_ns[0], imu_ns[0] + 300 * MS  # V1_02's GT rows lie on its IMU's stamps
    gt_csv = recording / "state_groundtruth_estimate0" / "data.csv"
    lines = gt_csv.read_text().splitlines(keepends=True)
    gt_csv.write_text("".join(r for r in lines if not r.startswith(f"{missing_row},")))
    assert len(gt_csv.read_text().splitlines()) == len(lines) - 1
    stderr = _make_bag(recording, tmp_path / "out", capsys)
    assert stderr == (f"vi3 make-bag: note: no frames in the ground truth's gap of 0.625 s from {t0 + 1_000 * MS} to "
                      f"{t0 + 1_625 * MS} ns (GT rows more than {MAX_GT_GAP_NS * 1e-9:g} s apart)\n")
    seq = read_asl(tmp_path / "out" / "asl")
    in_gap = (seq.stamps_ns > t0 + 1_000 * MS) & (seq.stamps_ns < t0 + 1_625 * MS)
    assert not in_gap.any() and seq.stamps_ns[0] == t0
    # Every other frame of the 20 Hz grid over the 2.5 s is rendered, those around the missing row too.
    grid = t0 + np.arange(51) * 50 * MS
    in_gap = (grid > t0 + 1_000 * MS) & (grid < t0 + 1_625 * MS)
    assert np.array_equal(seq.stamps_ns, grid[~in_gap]) and in_gap.sum() == 12
    assert seq.gt.covers(seq.stamps) and missing_row not in seq.gt.t_ns
    _assert_eval_scores_every_clip(tmp_path / "out" / "asl", len(seq), capsys)


def test_a_recording_whose_gt_starts_after_its_images_end_is_a_clear_error(euroc_fixture, tmp_path, capsys):
    """The real machine-hall fixture (IMU over 5 frames, GT rows 1 s later) has no span to render in."""
    code = cli.main(["make-bag", str(tmp_path / "out"), "--from-euroc", str(euroc_fixture)])
    stdout, stderr = capsys.readouterr()
    assert code == 2 and stdout == "" and not (tmp_path / "out").exists()
    assert stderr.startswith(f"vi3 make-bag: error: {euroc_fixture}: the IMU [") and \
        stderr.endswith("ns share less than one camera period\n")


def test_a_ground_truth_value_that_is_not_a_number_is_named_by_file_and_row(euroc_v102, tmp_path, capsys):
    """Issue 31: a NaN in the GT CSV was scipy's "`y` must contain only finite values." traceback (exit 1). Now one
    line naming the file, the row (counted after the header) and the column; nothing written."""
    recording = _cut(euroc_v102, tmp_path / "rec" / "mav0", gt_before_ns=0, gt_after_ns=0)
    gt_csv = recording / "state_groundtruth_estimate0" / "data.csv"
    lines = gt_csv.read_text().splitlines(keepends=True)
    cells = lines[7].split(",")
    lines[7] = ",".join([cells[0], cells[1], "nan", *cells[3:]])
    gt_csv.write_text("".join(lines))
    code = cli.main(["make-bag", str(tmp_path / "out"), "--from-euroc", str(recording), "--no-depth"])
    stdout, stderr = capsys.readouterr()
    assert code == 2 and stdout == "" and not (tmp_path / "out").exists()
    assert stderr == f"vi3 make-bag: error: {gt_csv}: row 7: 'nan' in column 3 is not a finite number\n"


def test_a_clip_without_the_imu_it_needs_is_skipped_and_named_and_the_run_goes_on(euroc_v102, tmp_path, capsys):
    """Issue 31: frames from the IMU's first sample on, evaluated with the IMU 20 ms late (``--calib-error
    0,0,0,20``): the first clip has no IMU at or before its first frame. It was "IMU of ... does not cover the clip",
    exit 2, no clip evaluated; now that clip is skipped as the node skips it (``imu_missing``), named in the JSON and
    the text, and every other clip is evaluated."""
    recording = _cut(euroc_v102, tmp_path / "rec" / "mav0", gt_before_ns=0, gt_after_ns=0)
    _make_bag(recording, tmp_path / "out", capsys)
    asl = tmp_path / "out" / "asl"
    args = ["eval", str(asl), "--calib-error", "0,0,0,20", "--no-progress"]
    assert cli.main([*args, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    n = len(clip_indices(len(read_asl(asl)), options=EvalOptions(clips="sliding"), chained=True))
    (skipped,) = report["skipped_clips"]
    assert skipped["reason"] == "imu_missing" and skipped["frames"][0] == 0 and report["n_clips"] == n - 1 >= 2
    assert cli.main(args) == 0
    assert f"skipped: frames 0-{skipped['frames'][1]} (imu_missing)" in capsys.readouterr().out


def test_ground_truth_with_unknown_biases_and_velocities_is_scored_without_them(euroc_v102, tmp_path, capsys):
    """Issue 39: a motion-capture trajectory written in the EuRoC layout has ``nan`` for the velocities and the six
    biases; it was refused whole (``row 1: 'nan' in column 12 is not a finite number``). Now the velocities come from
    the positions, the bias metrics are unknown (null, ``--``), every other metric is scored; a NaN position stays an
    error (the test above)."""
    recording = _cut(euroc_v102, tmp_path / "rec" / "mav0", gt_before_ns=0, gt_after_ns=0)
    gt_csv = recording / "state_groundtruth_estimate0" / "data.csv"
    lines = gt_csv.read_text().splitlines()
    gt_csv.write_text("\n".join([lines[0], *(",".join(r.split(",")[:8] + ["nan"] * 9) for r in lines[1:])]) + "\n")
    args = ["eval", str(recording), "--backbone", "gt", "--gt-noise", "0.001,0.05", "--no-progress"]
    assert cli.main([*args, "--json"]) == 0
    init = json.loads(capsys.readouterr().out)["init"]
    assert init["gyro_bias_err"] is None and init["v1_dir_deg"] is not None, init
    assert cli.main(args) == 0
    assert "Gyro-bias (rad/s) ↓" in capsys.readouterr().out
