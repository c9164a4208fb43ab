"""Issue 14: replay and eval under faults. A bad message is dropped and named, never fatal; every frame is checked
against the calibration; compressed images; one topic rule with --image-topic / --imu-topic; an output at --output
is always complete (temporary file, rename on success, OUT.partial.mcap or nothing otherwise); a non-zero exit with
the reason when nothing was produced; clear errors instead of tracebacks. Inputs are real bags and ASL folders
edited through rosbags / OpenCV."""

from __future__ import annotations

import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from test_replay import _calib_file, _clip_window, _converted_bag, _edited, _read, _statuses, _two_clips

from msg_adapters.stamps import stamp_to_ns
from msg_adapters.types import jazzy_types
from vi3_core.dataset.calib import CameraCalib, write_euroc_sensor_yaml
from vi3_core.dataset.generate import EUROC_CAM0
from vi3_core.types import ImuSamples
from vi3_ros.calibration import FrameMisfit, make_clip
from vi3_ros.cli import main as vi3_main
from vi3_ros.clip_buffer import RawClip

pytestmark = pytest.mark.slow  # every test here runs replays, evaluations or generated sequences

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def bag3(cache_dir):
    return _converted_bag(cache_dir, seconds=2.5, seed=1)


def _vi3(capsys, *args) -> tuple[int, str, str]:
    """``vi3 ARGS`` in this process: (exit status, stdout, stderr)."""
    capsys.readouterr()
    try:
        rc = vi3_main([str(a) for a in args])
    except SystemExit as exc:  # argparse
        rc = exc.code
    out, err = capsys.readouterr()
    return rc, out, err


def _replay(capsys, inp, out, *args, calib=None):
    calib = calib if calib is not None else _calib_file(Path(out).parent)
    return _vi3(capsys, "replay", inp, "--output", out, "--calib", calib, "--no-progress", *args)


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def _asl_copy(asl: Path, dst: Path) -> Path:
    shutil.copytree(asl, dst)
    return dst / "mav0"


def _frames(src: Path, dst: Path, edit, *, image_type: str = "sensor_msgs/msg/Image",
            image_topic: str = "/cam0/image_raw", until_ns: int | None = None, extra_image_topic: str | None = None):
    """Copy the rosbag2 ``src`` to ``dst``, images through ``edit(i, msg) -> msg`` written as ``image_type`` on
    ``image_topic`` (and on ``extra_image_topic`` too when given)."""
    store = jazzy_types().typestore
    with Reader(src) as reader, Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {}
        for c in reader.connections:
            if c.msgtype == "sensor_msgs/msg/Image":
                conns[c.topic] = [writer.add_connection(image_topic, image_type, typestore=store)]
                if extra_image_topic:
                    conns[c.topic].append(writer.add_connection(extra_image_topic, image_type, typestore=store))
            else:
                conns[c.topic] = [writer.add_connection(c.topic, c.msgtype, typestore=store)]
        i = 0
        for c, t, raw in reader.messages(stop=None if until_ns is None else until_ns + 1):
            msg = store.deserialize_cdr(raw, c.msgtype)
            if c.msgtype == "sensor_msgs/msg/Image":
                msg, i = edit(i, msg), i + 1
            for conn in conns[c.topic]:
                writer.write(conn, t, store.serialize_cdr(msg, conn.msgtype))
    return dst


def _compressed(fmt: str):
    types = jazzy_types()

    def edit(i, msg):
        gray = np.asarray(msg.data, np.uint8).reshape(msg.height, msg.width)
        ok, buf = cv2.imencode(".png" if fmt == "png" else ".jpg", gray)
        assert ok
        return types.make("sensor_msgs/msg/CompressedImage", header=msg.header, format=f"mono8; {fmt} compressed",
                          data=buf.reshape(-1))
    return edit


# ------------------------------------------------------------------------------------------- bad messages
def test_malformed_and_unsupported_frames_in_a_bag_are_dropped_and_named(bag3, tmp_path, capsys):
    asl, src = bag3

    def edit(i, msg):
        if i == 3:
            msg.step += 1  # step/size mismatch
        elif i == 5:
            msg.encoding = "yuv422"
        elif i == 7:  # a 0x0 frame: never undistorted into a black image and published ok
            msg.height = msg.width = msg.step = 0
            msg.data = np.zeros(0, np.uint8)
        return msg

    bag = _frames(src, tmp_path / "bad", edit)
    rc, out, err = _replay(capsys, bag, tmp_path / "out.mcap", "--json")
    assert rc == 0, err
    summary = json.loads(out)
    assert summary["drops"]["image_malformed"] == 1 and summary["drops"]["image_unsupported"] == 2
    msgs = _read(tmp_path / "out.mcap")
    diag = [s for m in msgs["/diagnostics"] for s in _statuses({"d": [m]}, "d")]
    text = " ".join(s.message for s in diag)
    assert "image_malformed" in text and "step" in text and "yuv422" in text  # the first drop of each reason
    assert diag[-1].values["drop_image_malformed"] == "1" and diag[-1].values["drop_image_unsupported"] == "2"
    assert any("image_malformed:1" in s.values["input_drops"] for s in _statuses(msgs))
    seq_ns = [stamp_to_ns(m.header.stamp) for m in msgs["/vi3_node/poses"]]
    assert seq_ns and all(t > _clip_window(asl, 0)[1] for t in seq_ns)  # later clips go on, metric


def test_missing_and_corrupt_pngs_of_an_asl_folder_are_dropped_and_named(bag3, tmp_path, capsys):
    asl, _ = bag3
    mav0 = _asl_copy(asl, tmp_path / "asl")
    pngs = sorted((mav0 / "cam0" / "data").glob("*.png"))
    pngs[2].unlink()
    pngs[4].write_bytes(b"\x89PNG\r\n\x1a\n" + os.urandom(100))
    rc, out, err = _replay(capsys, mav0.parent, tmp_path / "out.mcap", "--json")
    assert rc == 0, err
    assert json.loads(out)["drops"]["image_malformed"] == 2
    diag = " ".join(s.message for s in _statuses(_read(tmp_path / "out.mcap"), "/diagnostics"))
    assert pngs[2].name in diag and "not a readable PNG" in diag


def test_frames_that_do_not_fit_the_calibration_are_never_scored_or_published(bag3, tmp_path, capsys):
    """752x480 frames against a 640x480 calibration: replay drops every frame, naming it, publishes no result and
    exits 1 keeping only the statuses as OUT.partial.mcap; eval refuses, naming the frame."""
    asl, src = bag3
    c = EUROC_CAM0
    small = tmp_path / "cam640.yaml"
    write_euroc_sensor_yaml(CameraCalib(c.K, c.dist_model, c.dist, (640, 480), c.T_BC, c.rate_hz), small)
    rc, out, err = _replay(capsys, src, tmp_path / "out.mcap", calib=small)
    assert rc == 1 and "no clip produced a result" in err and "image_size_mismatch" in err
    assert not (tmp_path / "out.mcap").exists() and (tmp_path / "out.partial.mcap").exists()
    msgs = _read(tmp_path / "out.partial.mcap")
    assert "/vi3_node/poses" not in msgs
    assert any("752x480 but the calibration is for 640x480" in s.message for s in _statuses(msgs, "/diagnostics"))
    rc, out, err = _vi3(capsys, "eval", src, "--calib", small, "--no-progress")
    assert rc == 2 and "frame 0" in err and "752x480" in err and "640x480" in err


def test_a_calibration_that_arrives_late_checks_every_buffered_frame():
    """Frames buffered before any calibration: the clip is checked frame by frame when processed."""
    images = tuple(np.zeros((480, 752), np.uint8) for _ in range(7)) + (np.zeros((480, 640), np.uint8),)
    raw = RawClip(0, np.arange(8) * 0.1, np.arange(8) * 100_000_000, images,
                  ImuSamples(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3))))
    with pytest.raises(FrameMisfit, match=r"frame 7 \(stamp 700000000 ns\): frame is 640x480"):
        make_clip(raw, EUROC_CAM0)


# ------------------------------------------------------------------------------------------- compressed, topics
@pytest.mark.parametrize("fmt", ["png", "jpeg"])
def test_compressed_images_replay_and_eval(bag3, tmp_path, capsys, fmt):
    asl, src = bag3
    bag = _frames(src, tmp_path / "compressed", _compressed(fmt), image_type="sensor_msgs/msg/CompressedImage",
                  image_topic="/cam0/image_raw/compressed", until_ns=_two_clips(asl))
    # found as the only image topic; the gate is open: this checks decoding, not which clips may claim a scale
    rc, out, err = _replay(capsys, bag, tmp_path / "out.mcap", "--json", "--param", "max_scale_sigma=10")
    assert rc == 0, err
    assert json.loads(out)["results"] == 2
    if fmt == "png":  # lossless: the same input as the raw bag, so eval scores it
        rc, out, err = _vi3(capsys, "eval", bag, "--calib", _calib_file(tmp_path), "--no-progress", "--json",
                            "--independent")
        assert rc == 0, err
        assert json.loads(out)  # scored (the report schema is eval's)
        rc, _, err = _replay(capsys, bag, tmp_path / "raw.mcap", "--param", "image_transport=raw")
        assert rc == 2 and "sensor_msgs/msg/Image" in err and "no image topic" in err


def test_one_topic_rule_for_replay_and_eval(bag3, tmp_path, capsys):
    asl, src = bag3
    bag = _frames(src, tmp_path / "two", lambda i, m: m, image_topic="/left/image", extra_image_topic="/right/image",
                  until_ns=_two_clips(asl))
    calib = _calib_file(tmp_path)
    for cmd in (["replay", bag, "--output", tmp_path / "a.mcap", "--calib", calib, "--force"],
                ["eval", bag, "--calib", calib, "--independent"]):
        rc, _, err = _vi3(capsys, *cmd, "--no-progress")
        assert rc == 2 and "several image topics: /left/image (sensor_msgs/msg/Image), /right/image" in err
        assert "choose one with --image-topic" in err
        rc, _, err = _vi3(capsys, *cmd, "--no-progress", "--image-topic", "/right/image")
        assert rc == 0, err
        rc, _, err = _vi3(capsys, *cmd, "--no-progress", "--image-topic", "/right/image", "--imu-topic", "/imu9")
        assert rc == 2 and "topic '/imu9' is not in it; imu topics (sensor_msgs/msg/Imu): /imu0" in err
    one = _frames(src, tmp_path / "one", lambda i, m: m, image_topic="/camera/image", until_ns=_two_clips(asl))
    rc, _, err = _replay(capsys, one, tmp_path / "c.mcap")  # the parameter's /cam0/image_raw is absent: the only one
    assert rc == 0, err


# ------------------------------------------------------------------------------------------- outputs
def test_output_is_complete_or_absent(bag3, tmp_path, capsys):
    asl, src = bag3
    bag = _edited(src, tmp_path / "cut", lambda topic, t, m: [(t, m)], until_ns=_two_clips(asl))
    out = tmp_path / "out.mcap"
    junk = tmp_path / "junk.bag"
    junk.write_bytes(os.urandom(5000))
    rc, _, err = _replay(capsys, junk, out)
    assert rc == 2 and "cannot read the bag" in err and "Traceback" not in err
    assert not out.exists() and not (tmp_path / "out.partial.mcap").exists() and _leftovers(tmp_path) == []
    assert _replay(capsys, bag, out)[0] == 0
    first = out.stat().st_mtime_ns
    rc, _, err = _replay(capsys, bag, out)
    assert rc == 2 and "already exists" in err and "--force" in err
    assert _replay(capsys, bag, out, "--force")[0] == 0
    assert out.stat().st_mtime_ns != first and _read(out)["/vi3_node/poses"]
    rc, _, err = _replay(capsys, bag, tmp_path / "outdir", "--force")  # a rosbag2 directory replaces only a bag
    assert rc == 0 and (tmp_path / "outdir" / "metadata.yaml").is_file()
    (tmp_path / "notes").mkdir()
    rc, _, err = _replay(capsys, bag, tmp_path / "notes", "--force")
    assert rc == 2 and "not an MCAP file or a rosbag2 directory" in err
    assert _leftovers(tmp_path) == []


def _subprocess_replay(args: list, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "vi3_ros.cli", "replay", *map(str, args), "--no-progress"],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def _loading_torch(proc: subprocess.Popen) -> bool:
    """Whether the process has begun to load torch's libraries (it is importing the backbone's modules)."""
    try:
        return "libtorch" in Path(f"/proc/{proc.pid}/maps").read_text()
    except OSError:
        return False


@pytest.mark.parametrize("moment", ["loading", "replaying", "finished"])
def test_sigterm_at_any_moment_ends_143_with_what_was_kept_and_no_hidden_folder(cache_dir, tmp_path, moment):
    """SIGTERM while torch loads (before the backbone exists), a clip or two into the replay, and once the output
    has been moved into place (the process then prints its summary and exits): always status 128 + 15, no hidden
    work folder, no traceback, and stderr says what is on disk, which is exactly what is there."""
    if not Path(f"/proc/{os.getpid()}/maps").exists():
        pytest.skip("needs /proc to see when the process loads torch")
    # 10 s (14 clips, as test_online's sequence): the 4 s bag of before ended within the second after its work folder
    # appeared once each frame was tracked only once
    asl, src = _converted_bag(cache_dir, seconds=10.0, seed=0)
    out, partial = tmp_path / "out.mcap", tmp_path / "out.partial.mcap"
    proc = _subprocess_replay([src, "--output", out, "--calib", _calib_file(tmp_path)])
    ready = {"loading": lambda: _loading_torch(proc), "replaying": lambda: _leftovers(tmp_path),
             "finished": out.exists}[moment]
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None and not ready():
        time.sleep(0.01)
    if moment == "replaying":
        time.sleep(1.0)  # the hidden work folder appears before the backbone is loaded: a clip or two further
    assert proc.poll() is None or moment == "finished", proc.communicate()[1]
    proc.send_signal(signal.SIGTERM)  # nothing when it has already exited (a fast machine, moment "finished")
    _, err = proc.communicate(timeout=60)
    if moment == "finished" and proc.returncode == 0:  # it ended before the signal: complete and said so
        assert _read(out)["/vi3_node/poses"] and not partial.exists() and _leftovers(tmp_path) == []
        return
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "interrupted by SIGTERM" in err and "Traceback" not in err
    assert _leftovers(tmp_path) == []
    if moment == "loading":
        assert "nothing was written" in err and not out.exists() and not partial.exists()
    elif out.exists():  # the replay had finished (a fast machine): complete, and said so
        assert "is complete" in err or "after the command finished" in err, err
        assert not partial.exists() and _read(out)["/vi3_node/poses"]
    elif partial.exists():  # what was published before the signal, readable, and said so
        assert moment == "replaying" and f"kept what was produced in {partial}" in err
        assert "/diagnostics" in _read(partial)
    else:  # the signal came before the first output message
        assert moment == "replaying" and "nothing was written" in err


def test_a_full_disk_is_a_clear_error(bag3, tmp_path):
    """The output file system refuses to grow (RLIMIT_FSIZE, as a full disk does with ENOSPC)."""
    asl, src = bag3

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (50_000, 50_000))

    proc = _subprocess_replay([src, "--output", tmp_path / "out.mcap", "--calib", _calib_file(tmp_path),
                               "--param", "depth_frames=all"], preexec_fn=limit)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 2, err
    assert "File too large" in err and "Traceback" not in err
    assert f"replay output {tmp_path / 'out.mcap'}: cannot write it (File too large)" in err  # the file named
    assert not (tmp_path / "out.mcap").exists() and _leftovers(tmp_path) == []


def test_clear_errors_instead_of_tracebacks(bag3, tmp_path, capsys):
    asl, src = bag3
    cases = {"folder": (src, tmp_path / "missing" / "out.mcap", None, "folder {} does not exist"),
             "empty mcap": (tmp_path / "empty.mcap", tmp_path / "o1.mcap", None, "it is empty (0 bytes)"),
             "png calib": (src, tmp_path / "o2.mcap", tmp_path / "calib.png", "not a text file"),
             "dir calib": (src, tmp_path / "o3.mcap", tmp_path, "is a directory, not a calibration file"),
             "bad focal": (src, tmp_path / "o4.mcap", tmp_path / "neg.yaml", "focal length fu = -458.654")}
    (tmp_path / "empty.mcap").touch()
    cv2.imwrite(str(tmp_path / "calib.png"), np.zeros((4, 4), np.uint8))
    _calib_file(tmp_path)
    (tmp_path / "neg.yaml").write_text((tmp_path / "cam0_sensor.yaml").read_text().replace("458.654", "-458.654"))
    for name, (inp, out, calib, expect) in cases.items():
        rc, _, err = _replay(capsys, inp, out, calib=calib or tmp_path / "cam0_sensor.yaml")
        assert rc == 2 and expect.format(Path(out).parent) in err and "Traceback" not in err, (name, err)
    rc, _, err = _replay(capsys, src, tmp_path / "o5.mcap", "--device", "cuda")
    assert rc == 2 and "sees no CUDA GPU" in err
    rc, _, err = _vi3(capsys, "eval", src, "--calib", tmp_path / "cam0_sensor.yaml", "--device", "cuda")
    assert rc == 2 and "sees no CUDA GPU" in err
    rc, _, err = _replay(capsys, src, tmp_path / "o6.mcap", "--mode", "cond")
    assert rc == 2 and "backbones that can: pi3x, da3" in err
    rc, _, err = _vi3(capsys, "eval", src, "--max-clips", "0")
    assert rc == 2 and "--max-clips: must be >= 1" in err
    if os.access("/sys", os.W_OK) and not _sys_is_read_only():
        pytest.skip("no read-only folder here")
    rc, _, err = _replay(capsys, src, Path("/sys/out.mcap"), calib=tmp_path / "cam0_sensor.yaml")
    assert rc == 2 and "cannot write into /sys" in err
    assert _leftovers(tmp_path) == []


def _sys_is_read_only() -> bool:
    try:
        Path("/sys/.vi3-probe").mkdir()
    except OSError:
        return True
    Path("/sys/.vi3-probe").rmdir()
    return False


def test_nothing_produced_exits_non_zero_with_the_reason(bag3, tmp_path, capsys):
    """16-bit frames (every frame dropped), an empty camera CSV and an IMU CSV with a short row."""
    asl, _ = bag3
    mono16 = _asl_copy(asl, tmp_path / "mono16")
    for png in (mono16 / "cam0" / "data").glob("*.png"):
        cv2.imwrite(str(png), cv2.imread(str(png), cv2.IMREAD_UNCHANGED).astype(np.uint16) * 256)
    rc, out, err = _replay(capsys, mono16.parent, tmp_path / "a.mcap", "--json")
    summary = json.loads(out, parse_constant=lambda c: pytest.fail(f"{c} is not JSON"))
    assert rc == 1 and summary["results"] == 0 and summary["median_latency_ms"] is None
    n = summary["frames"]
    assert n > 40 and f"no clip was completed from {n} frames (drops: image_unsupported:{n})" in err
    assert "uint16" in " ".join(s.message for s in _statuses(_read(tmp_path / "a.partial.mcap"), "/diagnostics"))

    empty = _asl_copy(asl, tmp_path / "empty")
    (empty / "cam0" / "data.csv").write_text("#timestamp [ns],filename\n")
    rc, _, err = _replay(capsys, empty.parent, tmp_path / "b.mcap")
    assert rc == 1 and "the input has no camera frames" in err and not (tmp_path / "b.mcap").exists()

    short = _asl_copy(asl, tmp_path / "short")
    lines = (short / "imu0" / "data.csv").read_text().splitlines()
    lines[5] = ",".join(lines[5].split(",")[:4])
    (short / "imu0" / "data.csv").write_text("\n".join(lines) + "\n")
    rc, _, err = _replay(capsys, short.parent, tmp_path / "c.mcap")
    assert rc == 2 and "imu0/data.csv: the number of columns changed from 7 to 4 at row 5" in err
    assert _leftovers(tmp_path) == []
