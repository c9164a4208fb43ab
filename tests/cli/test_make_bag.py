"""``vi3 make-bag``: clear errors on stderr for bad arguments and outputs, nothing left behind by errors, Ctrl-C or
SIGTERM (and stale staging folders of killed runs removed), frames streamed to disk a block at a time, and
sequences rendered along a real EuRoC recording with its IMU carried unchanged."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from vi3_core.dataset.asl import read_asl, read_groundtruth, read_imu
from vi3_core.dataset.calib import load_calib
from vi3_core.dataset.generate import BLOCK_NS, CAM_PERIOD_NS, STAGING_PREFIX, SequenceSpec, write_sequence
from vi3_ros import cli
from vi3_ros.io.reader import open_sequence

pytestmark = pytest.mark.slow  # every test here runs replays, evaluations or generated sequences

REPO = Path(__file__).resolve().parents[2]


def _cli(argv: list[str], capsys) -> tuple[int, str, str]:
    code = cli.main(["make-bag", *argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("args, reason", [
    (["--seconds", "-1"], "seconds must be a finite number >= 0.05"),
    (["--seconds", "nan"], "seconds must be a finite number >= 0.05"),
    (["--seconds", "inf"], "seconds must be a finite number >= 0.05"),
    (["--seconds", "0"], "nothing to generate"),
    (["--seed", "-5"], "seed must be an integer >= 0, got -5"),
    (["--from-euroc", "nowhere", "--motion", "easy"], "--motion: only for generated sequences"),
    (["--from-euroc", "nowhere"], "not an EuRoC mav0 folder"),
])
def test_bad_arguments_are_one_clear_line_on_stderr_and_produce_nothing(tmp_path, capsys, args, reason):
    out = tmp_path / "out"
    code, stdout, stderr = _cli([str(out), *args], capsys)
    assert code == 2 and stdout == ""
    assert stderr.startswith("vi3 make-bag: error: ") and reason in stderr and "Traceback" not in stderr
    assert not out.exists()


def test_output_onto_a_file_is_a_clear_error(tmp_path, capsys):
    target = tmp_path / "taken"
    target.write_text("not a folder")
    code, stdout, stderr = _cli([str(target), "--seconds", "0.3"], capsys)
    assert code == 2 and stdout == "" and f"{target}: is a file" in stderr
    assert target.read_text() == "not a folder"


def test_read_only_folder_is_a_clear_error(tmp_path, capsys):
    """A folder the user cannot write into (root writes into any folder with mode 0555, so as root: /sys, which
    refuses new entries to everyone)."""
    if os.geteuid() == 0:
        parent = Path("/sys")
        if not (parent / "kernel").is_dir():
            pytest.skip("running as root without a sysfs /sys to stand in for a read-only folder")
    else:
        parent = tmp_path / "ro"
        parent.mkdir()
        parent.chmod(0o555)
    out = parent / "vi3_make_bag_out"
    code, stdout, stderr = _cli([str(out), "--seconds", "0.3"], capsys)
    assert code == 2 and stdout == "" and not out.exists()
    assert stderr.startswith(f"vi3 make-bag: error: cannot write {out}: ") and "Traceback" not in stderr
    assert "Permission denied" in stderr or "Operation not permitted" in stderr


def _start(out: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "vi3_ros.cli", "make-bag", str(out), "--seconds", "30",
                             "--no-depth", *extra], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)


def _wait_for_frames(out: Path, proc: subprocess.Popen, timeout: float = 60.0) -> None:
    """Until the run has written frames into its staging folder."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if list(out.glob(f"{STAGING_PREFIX}*/asl/mav0/cam0/data/*.png")):
            return
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.1)
    proc.kill()
    raise AssertionError("make-bag wrote no frame in time")


@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_mid_run_leaves_no_partial_output(tmp_path, sig, code):
    out = tmp_path / "out"
    proc = _start(out)
    _wait_for_frames(out, proc)
    t = time.monotonic()
    proc.send_signal(sig)
    stdout, stderr = proc.communicate(timeout=30)
    assert time.monotonic() - t < 10.0
    assert proc.returncode == code, stderr
    assert f"interrupted by {sig.name}" in stderr and "Traceback" not in stderr and stdout == ""
    assert not out.exists()  # the run made it and nothing is left in it


def test_a_later_run_removes_the_staging_folders_of_killed_runs(tmp_path, capsys):
    out = tmp_path / "out"
    proc = _start(out)
    _wait_for_frames(out, proc)
    proc.kill()  # SIGKILL: no cleanup possible
    proc.communicate()
    stale = list(out.glob(f"{STAGING_PREFIX}*"))
    assert len(stale) == 1 and stale[0].name.startswith(f"{STAGING_PREFIX}{proc.pid}.")
    live = out / f"{STAGING_PREFIX}{os.getpid()}.concurrent"  # a run still going: kept
    live.mkdir()
    code, stdout, stderr = _cli([str(out), "--seconds", "0.3", "--no-depth"], capsys)
    assert code == 0, stderr
    assert not stale[0].exists() and live.is_dir()
    assert sorted(p.name for p in out.iterdir()) == sorted(["asl", "ros1.bag", "mcap", "camchain-imucam.yaml",
                                                             live.name])


def test_frames_stream_to_disk_a_block_at_a_time(tmp_path):
    """At most two blocks of frames are in flight: when a block is handed on, the frames on disk are those of the
    blocks handed on so far plus at most the next block's (memory does not grow with the length)."""
    mav0 = tmp_path / "mav0"
    seen: list[tuple[int, int, int]] = []

    def on_block(block):
        on_disk = len(list((mav0 / "cam0" / "data").glob("*.png")))
        seen.append((int(block.cam_ns[0]), len(block.cam_ns), on_disk))
        assert len(block.images) == len(block.cam_ns) and block.images[0].shape == (480, 752)
        assert np.all(np.diff(block.imu_ns) > 0) and block.imu_ns[-1] - block.imu_ns[0] < BLOCK_NS

    write_sequence(mav0, SequenceSpec(seconds=5.0, seed=1, with_depth=False), on_block=on_block)
    frames_per_block = BLOCK_NS // CAM_PERIOD_NS
    handed = np.cumsum([n for _, n, _ in seen])
    assert len(seen) >= 3 and handed[-1] == 101 and [s for s, _, _ in seen] == sorted(s for s, _, _ in seen)
    for (_, _, on_disk), done in zip(seen, handed):
        assert done <= on_disk <= done + frames_per_block
    assert len(read_asl(mav0)) == 101


def test_from_euroc_renders_along_the_real_trajectory_and_carries_the_imu_unchanged(euroc_v102, tmp_path, capsys):
    out = tmp_path / "v102"
    code, stdout, stderr = _cli([str(out), "--from-euroc", str(euroc_v102), "--start", "10", "--seconds", "1",
                                 "--no-depth"], capsys)
    assert code == 0 and stderr == "", stderr
    seq = read_asl(out / "asl")
    src_ns, src_imu = read_imu(euroc_v102)
    src_gt = read_groundtruth(euroc_v102)
    # Frames at 20 Hz on the IMU's ns grid, inside the span both IMU and GT cover, 10 s into it.
    span0 = max(src_ns[0], src_gt.t_ns[0])
    assert len(seq) == 21 and np.all(np.diff(seq.stamps_ns) == 50_000_000) and np.isin(seq.stamps_ns, src_ns).all()
    assert seq.stamps_ns[0] == span0 + 10_000_000_000
    # IMU: the recording's samples, bit for bit, from 1 s before the first frame to 0.1 s after the last.
    rows = np.searchsorted(src_ns, seq.imu_ns)
    assert np.array_equal(src_ns[rows], seq.imu_ns) and np.all(np.diff(rows) == 1)
    assert np.array_equal(seq.imu.gyro, src_imu.gyro[rows]) and np.array_equal(seq.imu.accel, src_imu.accel[rows])
    assert seq.imu_ns[0] == seq.stamps_ns[0] - 1_000_000_000 and seq.imu_ns[-1] == seq.stamps_ns[-1] + 100_000_000
    # GT: the recording's rows over that span (poses, velocities, biases), 40 Hz.
    g = np.searchsorted(src_gt.t_ns, seq.gt.t_ns)
    assert np.array_equal(src_gt.t_ns[g], seq.gt.t_ns) and len(g) == 85
    np.testing.assert_allclose(seq.gt.T_WB, src_gt.T_WB[g], atol=1e-12)
    assert np.array_equal(seq.gt.v_WB, src_gt.v_WB[g]) and np.array_equal(seq.gt.ba, src_gt.ba[g])
    # The recording's own calibration files; the bags carry the same streams.
    for rel in ("cam0/sensor.yaml", "imu0/sensor.yaml", "body.yaml"):
        assert (out / "asl" / "mav0" / rel).read_bytes() == (euroc_v102 / rel).read_bytes()
    np.testing.assert_allclose(seq.calib.T_BC, load_calib(euroc_v102 / "cam0" / "sensor.yaml").T_BC)
    for bag in (out / "ros1.bag", out / "mcap"):
        other = open_sequence(bag, calib=out / "camchain-imucam.yaml")
        assert np.array_equal(other.imu.accel, seq.imu.accel) and np.array_equal(other.stamps_ns, seq.stamps_ns)
        assert np.array_equal(other.image(20), seq.image(20))
    assert seq.image(10).std() > 20  # a textured scene around the drone
