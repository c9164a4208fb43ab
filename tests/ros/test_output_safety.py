"""Issue 26, what is written: nothing destroyed (an output that is, lies inside or contains an input is refused,
--force or not), nothing silently replaced (one run at a time per output), no stale partial beside a complete
output, a clip's messages written as one unit, Ctrl-C / SIGTERM on a serial `vi3 eval` keeping what finished, and
exit 130 without a traceback in every window of a `vi3` command. Real bags, real subprocess runs of the CLI."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from test_eval_ray import _read_until
from test_make_bag import _start, _wait_for_frames
from test_replay import _calib_file, _converted_bag, _edited, _read, _two_clips
from test_replay_faults import _leftovers, _replay, _vi3

from msg_adapters.diagnostics import DiagStatus, Level, diagnostic_array
from msg_adapters.poses import pose_array
from msg_adapters.types import jazzy_types
from vi3_core.dataset.generate import cached_sequence
from vi3_ros import interrupts
from vi3_ros.io.output_lock import OutputLock, lock_path
from vi3_ros.replay import McapSink, partial_path

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def bag3(cache_dir):
    return _converted_bag(cache_dir, seconds=2.5, seed=1)


@pytest.fixture(scope="module")
def two_clips(bag3, tmp_path_factory) -> Path:
    """A rosbag2 MCAP folder of bag3's first two clips."""
    asl, src = bag3
    return _edited(src, tmp_path_factory.mktemp("two") / "cut", lambda topic, t, m: [(t, m)],
                   until_ns=_two_clips(asl))


def _bytes(path: Path) -> dict[str, bytes]:
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    return {str(f.relative_to(path.parent)): f.read_bytes() for f in files}


# ------------------------------------------------------------------------------------------- 1: inputs are safe
def test_an_output_that_is_inside_or_contains_an_input_is_refused_even_with_force(two_clips, bag3, tmp_path,
                                                                                   capsys):
    asl, _ = bag3
    calib = _calib_file(tmp_path)
    single = tmp_path / "o" / "self.mcap"
    single.parent.mkdir()
    shutil.copyfile(next(two_clips.glob("*.mcap")), single)
    folder = shutil.copytree(two_clips, tmp_path / "bag2")
    (tmp_path / "link.mcap").symlink_to(single)
    shutil.copyfile(single, tmp_path / "x.partial.mcap")
    before = {**_bytes(single), **_bytes(folder), **_bytes(calib)}
    cases = [(single, single, f"replay output {single} is the input {single}"),
             (folder, folder, f"replay output {folder} is the input {folder}"),
             (single, tmp_path / "link.mcap", "link.mcap is the input"),  # another name of the same file
             (single, tmp_path / "o", "o contains the input"),
             (asl, asl / "out.mcap", "out.mcap is inside the input"),
             (tmp_path / "x.partial.mcap", tmp_path / "x.mcap", "the partial output of"),
             (single, calib, "is the input")]
    for inp, out, says in cases:
        rc, _, err = _replay(capsys, inp, out, "--force", calib=calib)
        assert rc == 2 and says in err and "Traceback" not in err, (inp, out, err)
    assert {**_bytes(single), **_bytes(folder), **_bytes(calib)} == before
    rc, _, err = _vi3(capsys, "eval", single, "--calib", calib, "--json-out", single, "--no-progress")
    assert rc == 2 and f"--json-out {single} is the input" in err
    assert {**_bytes(single), **_bytes(folder), **_bytes(calib)} == before


# ------------------------------------------------------------------------------------------- 2: one run per output
def test_a_second_replay_onto_an_output_being_written_fails_at_once_naming_the_first(two_clips, tmp_path, capsys):
    out = tmp_path / "x.mcap"
    holder = OutputLock(out, what="replay output")  # another run: the lock is the real one, held by another fd
    holder.acquire()
    try:
        t = time.monotonic()
        for extra in ((), ("--force",)):
            rc, _, err = _replay(capsys, two_clips, out, *extra)
            assert rc == 2 and f"replay output {out} is being written by another run (pid {os.getpid()}" in err
        assert time.monotonic() - t < 30 and not out.exists() and not partial_path(out).exists()
    finally:
        holder.release()
    assert not lock_path(out).exists()
    lock_path(out).write_text("pid 1, started long ago\n")  # left by a run that was killed: it holds no lock
    rc, _, err = _replay(capsys, two_clips, out)
    assert rc == 0, err
    assert out.is_file() and _leftovers(tmp_path) == []


def test_a_second_make_bag_onto_one_folder_fails_at_once_naming_the_first(tmp_path, capsys):
    out = tmp_path / "out"
    first = _start(out)
    try:
        _wait_for_frames(out, first)
        rc = subprocess.run([sys.executable, "-m", "vi3_ros.cli", "make-bag", str(out), "--seconds", "0.3",
                             "--no-depth", "--overwrite"], cwd=REPO, capture_output=True, text=True, timeout=120)
        assert rc.returncode == 2 and f"make-bag output {out} is being written by another run (pid {first.pid}" \
            in rc.stderr, rc.stderr
        assert first.poll() is None  # the first run goes on
    finally:
        first.send_signal(signal.SIGTERM)
        first.communicate(timeout=60)
    assert not out.exists() and _leftovers(tmp_path) == []


# ------------------------------------------------------------------------------------------- 4: partials
def test_a_complete_replay_removes_the_partial_an_earlier_run_left(two_clips, tmp_path, capsys):
    """The earlier run produced no result (a calibration for another frame size): its statuses were kept as
    out.partial.mcap; the retry completes and nothing stale stays beside its output."""
    out = tmp_path / "out.mcap"
    wrong = tmp_path / "wrong.yaml"
    wrong.write_text(_calib_file(tmp_path).read_text().replace("752, 480", "640, 480"))
    rc, _, err = _replay(capsys, two_clips, out, calib=wrong)
    assert rc == 1 and partial_path(out).is_file(), err
    rc, _, err = _replay(capsys, two_clips, out)
    assert rc == 0, err
    assert out.is_file() and not partial_path(out).exists() and _leftovers(tmp_path) == []


def test_a_clip_is_written_whole_or_not_at_all(tmp_path):
    """A clip's geometry waits for its ~/status; a run interrupted in between keeps neither (the diagnostics,
    published outside clips, are kept); a signal while a clip is written is raised after it."""
    types = jazzy_types()
    sink = McapSink(tmp_path / "a.mcap", types=types)
    sink.publish("poses", _poses(types), 5)
    sink.publish("diagnostics", _status_msg(types), 6)
    msgs = _read(sink.abandon())
    assert "/vi3_node/poses" not in msgs and len(msgs["/diagnostics"]) == 1
    sink = McapSink(tmp_path / "b.mcap", types=types)
    sink.publish("poses", _poses(types), 5)
    with interrupts.trapped() as trap:
        with pytest.raises(KeyboardInterrupt):
            with interrupts.held():
                os.kill(os.getpid(), signal.SIGINT)  # while a clip is written: recorded, raised after
                time.sleep(0.05)
                sink.publish("status", _status_msg(types), 5)
        assert trap.signum == signal.SIGINT
    msgs = _read(sink.abandon())
    assert len(msgs["/vi3_node/poses"]) == 1 and len(msgs["/vi3_node/status"]) == 1


def _poses(types):
    return pose_array(np.eye(4)[None], stamp_ns=5, frame_id="vi3_clip", types=types)


def _status_msg(types):
    return diagnostic_array([DiagStatus(Level.OK, "vi3: clip", "init: ok", "vi3_clip", {})], stamp_ns=5, types=types)


# ------------------------------------------------------------------------------------------- 3: serial eval
@pytest.mark.parametrize("sig, chained", [(signal.SIGINT, False), (signal.SIGTERM, True)])
def test_a_signal_on_a_serial_eval_writes_the_finished_clips_marked_partial(cache_dir, tmp_path, sig, chained):
    seq = cached_sequence(cache_dir, seconds=2.0, seed=3)
    json_out = tmp_path / "eval.json"
    mode = ["--independent"] if not chained else []
    proc = subprocess.Popen([sys.executable, "-m", "vi3_ros.cli", "eval", str(seq), *mode, "--clips", "sliding",
                             "--param", "hop=2", "--json-out", str(json_out)], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    seen = _read_until(proc, rb" ([1-9]|1[0-3])/14 ", timeout_s=240)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=120)
    err = (seen + err).decode()
    assert proc.returncode == 128 + sig, err
    assert "Traceback" not in err and f"interrupted by {sig.name}; what had finished is written" in err
    obj = json.loads(json_out.read_text())
    assert obj["partial"] is True and 1 <= obj["n_clips"] < 14, obj.get("errors")
    assert obj["errors"] == [f"{obj['sequence']}: interrupted: {obj['n_clips']} of 14 clips evaluated"]
    assert ("chained" in obj) == chained and "PARTIAL" in out.decode()


# ------------------------------------------------------------------------------------------- 8: every window
def _mapped(proc: subprocess.Popen, name: str) -> bool:
    """Whether the process has loaded a shared library whose path contains ``name``."""
    try:
        return name in Path(f"/proc/{proc.pid}/maps").read_text()
    except OSError:
        return False


@pytest.mark.parametrize("delay_s", [0.0, 0.1, 0.3])
def test_ctrl_c_in_the_first_moments_of_a_command_ends_130_without_a_traceback(tmp_path, delay_s):
    """``delay_s`` after the program began to load numpy (building its parser: the first ~0.3 s of any command,
    where Python's KeyboardInterrupt printed a traceback); earlier than that only the interpreter's own start runs,
    before any line of the program."""
    if not Path(f"/proc/{os.getpid()}/maps").exists():
        pytest.skip("needs /proc to see when the process loads numpy")
    proc = subprocess.Popen([sys.executable, "-m", "vi3_ros.cli", "make-bag", str(tmp_path / "out"), "--seconds",
                             "0.3"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and proc.poll() is None and not _mapped(proc, "_multiarray_umath"):
        time.sleep(0.002)
    time.sleep(delay_s)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err and "interrupted by SIGINT" in err, err
    assert not (tmp_path / "out").exists() and _leftovers(tmp_path) == []


@pytest.mark.parametrize("delay_s", [0.0, 0.002, 0.01, 0.03])
def test_ctrl_c_while_the_console_script_imports_the_program_ends_130_without_a_traceback(delay_s):
    """Issue 39: Ctrl-C in the first ~0.05 s, while the ``vi3`` console script imported the program, printed Python's
    KeyboardInterrupt traceback. The script's module (``vi3_ros.entry``) takes SIGINT before anything else loads: a
    signal ``delay_s`` into the imports that follow (the command line's, numpy's) ends the process quietly."""
    from importlib.metadata import entry_points

    (script,) = [e for e in entry_points(group="console_scripts") if e.name == "vi3"]
    assert script.value == "vi3_ros.entry:program"
    code = ("import vi3_ros.entry, os, signal, threading, time\n"
            f"threading.Timer({delay_s}, os.kill, (os.getpid(), signal.SIGINT)).start()\n"
            "from vi3_ros import cli\n"
            "cli.build_parser()\n"
            "time.sleep(10)\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 130, proc.stderr
    assert proc.stderr == "vi3: interrupted by SIGINT before the command started; nothing was written\n"


def test_ctrl_c_while_the_program_exits_ends_130_without_a_traceback():
    """The last milliseconds: a signal while the exit functions run (after the command's outputs are final)."""
    code = ("from vi3_ros import interrupts\n"
            "import atexit, os, signal, time\n"
            "interrupts.exit_on_signal()\n"
            "atexit.register(lambda: (os.kill(os.getpid(), signal.SIGINT), time.sleep(2)))\n"
            "interrupts.set_phase(interrupts.FINISHED)\n"
            "interrupts.end(0)\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 130, proc.stderr
    assert "interrupted by SIGINT after the command finished" in proc.stderr
    assert "Exception ignored" not in proc.stderr and "Traceback" not in proc.stderr
