"""What ``vi3 eval`` reads and writes: ground-truth depth in every supported form (or a named refusal), sequence
names, checks of every path before evaluating, partial results after a late failure, and chaining only contiguous
clips with every reset counted. Sequences are generated ones, re-assembled in ``tmp_path`` by symlinks."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from vi3_core.backbones import make_backbone
from vi3_core.dataset.asl import read_asl, sequence_name
from vi3_core.dataset.generate import cached_sequence
from vi3_core.dataset.sequence import make_clip, sample_clips
from vi3_core.eval import runner
from vi3_ros import cli
from vi3_ros.commands.eval import unique_names

pytestmark = pytest.mark.slow  # every test here runs replays, evaluations or generated sequences


@pytest.fixture(scope="module")
def generated(cache_dir) -> Path:
    return cached_sequence(cache_dir, seconds=2.0, seed=3)  # 41 frames with depth (as test_eval_runner's)


def assemble(src: Path, dst: Path, *, depth: bool = False, skip_image: int | None = None) -> Path:
    """``dst/mav0`` made of ``src``'s sensor folders (symlinks); its depth0/ only with ``depth``; cam0 without the
    image file of frame ``skip_image`` (still listed in cam0/data.csv)."""
    mav0 = dst / "mav0"
    mav0.mkdir(parents=True)
    for name in ("imu0", "state_groundtruth_estimate0", "body.yaml", *(["depth0"] if depth else [])):
        os.symlink(src / "mav0" / name, mav0 / name)
    if skip_image is None:
        os.symlink(src / "mav0" / "cam0", mav0 / "cam0")
    else:
        (mav0 / "cam0" / "data").mkdir(parents=True)
        for name in ("data.csv", "sensor.yaml"):
            os.symlink(src / "mav0" / "cam0" / name, mav0 / "cam0" / name)
        for k, png in enumerate(sorted((src / "mav0" / "cam0" / "data").glob("*.png"))):
            if k != skip_image:
                os.symlink(png, mav0 / "cam0" / "data" / png.name)
    return mav0


# ---- ground-truth depth -----------------------------------------------------------------------------------------

A_M, B = 2.0, 0.5  # the plane z = A_M + B x seen by cam0: z-depth A_M / (1 - B x_n) along normalised ray x_n


def _plane_raw_depth(calib) -> np.ndarray:
    """[H,W] float32 z-depth of the plane at every RAW (distorted) pixel of ``calib``."""
    w, h = calib.size
    v, u = np.mgrid[0:h, 0:w]
    xy = calib.undistort_points(np.column_stack([u.ravel(), v.ravel()]).astype(np.float64))
    return (A_M / (1.0 - B * xy[:, 0])).reshape(h, w).astype(np.float32)


def test_float_npy_depth_on_the_raw_grid_is_undistorted_by_nearest_neighbour(generated, tmp_path):
    """z-depth per raw pixel (``depth0/data/<ns>.npy``, no data.csv) lands on the undistorted grid through the
    undistortion map: it matches the plane there, and every value is one of the raw values."""
    seq0 = read_asl(generated)
    mav0 = assemble(generated, tmp_path / "npy")
    raw = _plane_raw_depth(seq0.calib)
    raw[200:240, 350:400] = np.nan  # no depth in a patch
    (mav0 / "depth0" / "data").mkdir(parents=True)
    for ns in seq0.stamps_ns[:2]:
        np.save(mav0 / "depth0" / "data" / f"{ns}.npy", raw)
    seq = read_asl(mav0)
    assert seq.depth_on_raw_grid and "float .npy" in seq.depth_gt and "2 of 41 frames" in seq.depth_gt
    depth = seq.gt_depth(0)
    K = seq.calib.undistorter().K
    x_n = (np.arange(depth.shape[1]) - K[0, 2]) / K[0, 0]
    truth = np.broadcast_to(A_M / (1.0 - B * x_n), depth.shape)
    valid = np.isfinite(depth)
    assert depth.shape == raw.shape and 0.95 < valid.mean() < 1.0
    assert np.abs(depth - truth)[valid].max() < 0.01  # one raw pixel of the plane's depth gradient
    assert np.isin(depth[valid], raw[np.isfinite(raw)]).all()  # nearest neighbour: no value invented
    assert np.abs(raw - truth)[np.isfinite(raw)].max() > 0.1  # read as if undistorted, it would be wrong
    clip = make_clip(seq, np.array([0, 1, 2]))
    assert np.isfinite(clip.gt.depth[:2]).any() and np.isnan(clip.gt.depth[2]).all()  # frame 2 has no depth


def test_png_depth_in_millimetres_and_with_a_stated_scale(generated, tmp_path):
    seq0 = read_asl(generated)
    w, h = seq0.calib.size
    mm = np.full((h, w), 2500, np.uint16)
    mm[:, 370:380] = 0  # no depth
    mav0 = assemble(generated, tmp_path / "mm")
    (mav0 / "depth0" / "data").mkdir(parents=True)
    cv2.imwrite(str(mav0 / "depth0" / "data" / f"{seq0.stamps_ns[0]}.png"), mm)
    seq = read_asl(mav0)
    assert "16-bit PNG (1000 per m)" in seq.depth_gt and seq.depth_on_raw_grid
    d = seq.gt_depth(0)
    assert np.nanmin(d) == np.nanmax(d) == pytest.approx(2.5) and np.isnan(d).any()
    # TUM RGB-D's 5000 per metre, on the undistorted grid, stated in sensor.yaml
    doc = {"depth_scale": 5000, "undistorted_K": seq0.calib.undistorter().K.reshape(-1).tolist()}
    (mav0 / "depth0" / "sensor.yaml").write_text(yaml.safe_dump(doc))
    seq = read_asl(mav0)
    assert not seq.depth_on_raw_grid and "5000 per m" in seq.depth_gt
    assert np.nanmax(seq.gt_depth(0)) == pytest.approx(0.5) and np.isnan(seq.gt_depth(0)[:, 370:380]).all()


@pytest.mark.parametrize("case", ["no_data", "no_match", "wrong_size", "eight_bit", "bad_scale"])
def test_unusable_depth_folder_is_named_not_ignored(generated, tmp_path, case):
    seq0 = read_asl(generated)
    w, h = seq0.calib.size
    mav0 = assemble(generated, tmp_path / case)
    data = mav0 / "depth0" / "data"
    data.mkdir(parents=True)
    ns = seq0.stamps_ns[0]
    expected = {"no_data": "neither data.csv nor a data/ folder", "no_match": "none of its 1 depth files",
                "wrong_size": "depth map is 10x8", "eight_bit": "single-channel 16-bit",
                "bad_scale": "depth_scale must be a positive number"}[case]
    if case == "no_data":
        data.rmdir()
    elif case == "no_match":
        np.save(data / "123.npy", np.ones((h, w), np.float32))
    elif case == "wrong_size":
        np.save(data / f"{ns}.npy", np.ones((8, 10), np.float32))
    elif case == "eight_bit":
        cv2.imwrite(str(data / f"{ns}.png"), np.ones((h, w), np.uint8))
    else:
        np.save(data / f"{ns}.npy", np.ones((h, w), np.float32))
        (mav0 / "depth0" / "sensor.yaml").write_text("depth_scale: -1\n")
    seq = read_asl(mav0)
    assert seq.depth_gt.startswith("unreadable: ") and expected in seq.depth_gt, seq.depth_gt
    assert seq.load_depth is None and make_clip(seq, np.arange(3)).gt.depth is None


# ---- names and outputs -------------------------------------------------------------------------------------------

def test_sequence_names_come_from_the_recordings_folder(tmp_path):
    for rel, name in (("room/asl/mav0", "room"), ("hall/mav0", "hall"), ("flat", "flat")):
        (tmp_path / rel).mkdir(parents=True)
        assert sequence_name(tmp_path / rel) == name
    assert unique_names(["room", "room", "sigma", "room_2"]) == ["room", "room_2", "sigma_2", "room_2_2"]


def test_same_named_inputs_get_unique_names_and_outputs_and_unreadable_depth_is_said(generated, tmp_path, capsys):
    a = assemble(generated, tmp_path / "a" / "room" / "asl")
    b = assemble(generated, tmp_path / "b" / "room" / "asl")
    (b / "depth0").mkdir()  # a depth folder with nothing usable in it
    out = tmp_path / "out"
    rc = cli.main(["eval", str(a.parent), str(b.parent), "--independent", "--max-clips", "1", "--no-progress",
                   "--json", "--plot", str(out / "eval.png"), "--export-tum", str(out / "tum")])
    captured = capsys.readouterr()
    obj = json.loads(captured.out)
    assert rc == 0, captured.err
    assert [s["sequence"] for s in obj["sequences"]] == ["room", "room_2"]
    assert obj["sequences"][0]["depth_gt"] == "none"
    assert obj["sequences"][1]["depth_gt"].startswith("unreadable: ") and obj["sequences"][1]["vi3"]["absrel"] is None
    assert "depth ground truth unreadable" in captured.err and str(b.parent) in captured.err
    for name in ("room", "room_2"):
        assert (out / f"eval_{name}.png").is_file() and (out / "tum" / name / "clip000_gt.txt").is_file()
    assert (out / "eval_sigma.png").is_file()


def test_bad_paths_are_found_before_any_clip_is_evaluated(generated, tmp_path, capsys):
    a = assemble(generated, tmp_path / "a")
    blocker = tmp_path / "file"
    blocker.write_text("")
    json_out = tmp_path / "out.json"
    for extra, named in (([str(a), "--plot", str(blocker / "eval.png")], str(blocker)),
                         ([str(a), str(tmp_path / "missing")], str(tmp_path / "missing")),
                         ([str(a), "--export-tum", str(blocker / "tum")], str(blocker)),
                         ([str(a), "--json-out", str(tmp_path)], str(tmp_path))):
        rc = cli.main(["eval", *extra, "--json-out", str(json_out)] if "--json-out" not in extra
                      else ["eval", *extra])
        err = capsys.readouterr().err
        assert rc == 2 and named in err, err
        assert "eval " not in err.replace("vi3 eval:", "")  # no progress bar: nothing was evaluated
        assert not json_out.exists()


def test_a_late_failure_writes_what_was_computed_and_says_it_is_partial(generated, tmp_path, capsys):
    """The sequence loses a frame of its second clip, and a TUM file of its first cannot be written: both are named,
    everything else is written."""
    broken = assemble(generated, tmp_path / "broken", skip_image=20)  # sliding clips: frames 0-14, 16-30
    tum = tmp_path / "tum"
    (tum / "clip000_base.txt").mkdir(parents=True)  # a folder where a file must go
    json_out = tmp_path / "eval.json"
    rc = cli.main(["eval", str(broken), "--independent", "--clips", "sliding", "--no-progress", "--param",
                   "max_scale_sigma=10", "--json-out", str(json_out), "--export-tum", str(tum)])  # gate open: plumbing
    captured = capsys.readouterr()
    assert rc == 2
    obj = json.loads(json_out.read_text())
    assert obj["partial"] is True and len(obj["errors"]) == 2, obj["errors"]
    assert obj["n_clips"] == 1 and obj["vi3"]["scale_traj"] is not None and "frames 16-30" in obj["error"]
    assert (tum / "clip000_gt.txt").is_file()
    assert "PARTIAL" in captured.out and "Scale (Traj.)" in captured.out and "clip000_base.txt" in captured.err


# ---- chaining ----------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def short(cache_dir) -> Path:
    return cached_sequence(cache_dir, seconds=2.5, seed=1, with_depth=False)  # 51 frames (as test_online's)


def test_chained_eval_defaults_to_contiguous_sliding_clips(short, capsys):
    assert cli.main(["eval", str(short), "--json", "--no-progress", "--max-clips", "2"]) == 0
    obj = json.loads(capsys.readouterr().out)
    # sliding, a clip every 14 frames (each shares its first frame with the one before; paper's would start at 36)
    assert [c["frames"] for c in obj["clips"]] == [[0, 14], [28, 42]]
    ch = obj["chained"]
    assert ch["applicable"] and ch["segments"] == 1 and len(ch["per_segment"]) == 1
    assert ch["frames"] == 8 * obj["status_counts"]["ok"]  # a clip is chained once the window claims its scale
    assert ch["per_segment"][0]["ate_m"] == ch["ate_m"]
    assert set(ch["independent_claimed_outliers"]) == {"count", "claimed", "share"}


def test_clips_seconds_apart_chain_only_through_a_trustworthy_bridge(cache_dir, capsys):
    """Paper clips seconds apart: the IMU bridges them (as it bridges clips a busy worker dropped) when the bridge's
    position uncertainty allows, else the far clip starts a new segment; never a jump scored as drift."""
    long = cached_sequence(cache_dir, seconds=10.0, seed=0, with_depth=False)  # as test_online's
    assert cli.main(["eval", str(long), "--json", "--no-progress", "--clips", "paper"]) == 0
    obj = json.loads(capsys.readouterr().out)
    ch, ok = obj["chained"], obj["status_counts"]["ok"]
    if ok:
        assert ch["applicable"] and 1 <= ch["segments"] <= ok and ch["frames"] == 8 * ok, ch
        assert all(s["drift_pct"] is None or s["drift_pct"] < 10.0 for s in ch["per_segment"]), ch
    else:
        assert not ch["applicable"] and "no trajectory" in ch["reason"], ch


def test_a_rejected_first_clip_is_logged_and_no_reset_is_invented(short, tmp_path):
    """A first clip whose IMU has a NaN is rejected and never placed in odom; the next clip starts the window (there
    was none to reset): the decision log and the counts say exactly that."""
    mav0 = assemble(short, tmp_path / "nan_imu")
    imu = mav0 / "imu0"
    imu.unlink()
    shutil.copytree(short / "mav0" / "imu0", imu)
    lines = (imu / "data.csv").read_text().splitlines()
    k = 1 + 20 + 100  # header, 0.1 s of IMU before the first frame, then 0.5 s: inside the first clip (0-0.7 s)
    row = lines[k].split(",")
    row[4] = "nan"
    lines[k] = ",".join(row)
    (imu / "data.csv").write_text("\n".join(lines) + "\n")
    seq = read_asl(mav0)
    clips = sample_clips(len(seq), mode="sliding")[:2]
    evals, run = runner.evaluate_online(seq, make_backbone("classical"), clips=clips,
                                        options=runner.EvalOptions(progress=False))
    assert evals[0].status == "rejected" and "NaN" in run.decisions[0], run.decisions
    assert run.decisions[1].startswith("window 1 clips") and "reset" not in run.decisions[1], run.decisions
    assert run.resets == 0 and run.segment_starts == [], (run.decisions, run.segment_starts)
