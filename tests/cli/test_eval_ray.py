"""``vi3 eval --ray`` on a local Ray instance (2 CPUs, started once for the module) against the serial run on a short
generated sequence: the same JSON, text, plots and TUM files for independent and chained runs; a worker killed in
the middle of a clip is replaced and its task run again to the same result; a clip that cannot be read is reported
while the others are written; Ctrl-C returns what had finished, marked partial; without Ray, --ray says how to
install it."""

from __future__ import annotations

import functools
import json
import os
import re
import selectors
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_eval_inputs import assemble

from vi3_core.backbones import make_backbone
from vi3_core.backbones.classical import ClassicalBackbone
from vi3_core.dataset.asl import read_asl
from vi3_core.dataset.generate import cached_sequence
from vi3_core.eval import distributed, report, runner
from vi3_ros import cli

pytestmark = pytest.mark.slow  # every test here runs replays, evaluations or generated sequences

REPO = Path(__file__).resolve().parents[2]
HOP = ["--clips", "sliding", "--param", "hop=8"]  # 4 overlapping clips of 41 frames: 0-14, 8-22, 16-30, 24-38


@pytest.fixture(scope="module")
def sequence_dir(cache_dir) -> Path:
    return cached_sequence(cache_dir, seconds=2.0, seed=3)  # as test_eval_runner's and test_eval_inputs'


@pytest.fixture(scope="module")
def ray_module():
    return pytest.importorskip("ray", reason="Ray is not installed (pip install '.[ray]', part of the test extra)")


@pytest.fixture(scope="module")
def local_ray(ray_module):
    """One local Ray instance of 2 CPUs for the module; `vi3 eval --ray` uses the instance it finds connected."""
    ray = ray_module
    ray.init(num_cpus=2, include_dashboard=False)
    # The test's own backbone below must reach the workers by value: they cannot import this test module.
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    yield
    ray.shutdown()


def _eval(args: list, capsys) -> tuple[int, str, str]:
    try:
        rc = cli.main(["eval", *map(str, args)])
    except SystemExit as exc:  # argparse (--ray's ADDRESS is checked as it is parsed)
        rc = exc.code
    out, err = capsys.readouterr()
    return rc, out, err


def test_independent_clips_on_ray_match_the_serial_run(local_ray, sequence_dir, tmp_path, capsys):
    runs = {}
    for name, extra in (("serial", ["--no-progress"]), ("ray", ["--ray"])):
        out = tmp_path / name
        # the gate open: serial and Ray must agree on claimed clips too, whoever claims them
        rc, text, err = _eval([sequence_dir, "--independent", *HOP, "--param", "max_scale_sigma=10", "--json-out",
                               out / "eval.json", "--plot",
                               out / "eval.png", "--export-tum", out / "tum", *extra], capsys)
        assert rc == 0, err
        runs[name] = (out, text, err)
    (serial, text, _), (dist, dist_text, err) = runs["serial"], runs["ray"]
    obj = json.loads((serial / "eval.json").read_text())
    assert obj["n_clips"] == 4 and obj["n_ok"] >= 1, obj["status_counts"]
    assert text == dist_text
    files = sorted(p.relative_to(serial) for p in serial.rglob("*") if p.is_file())
    assert len(files) >= 2 + 2 + 4 * 2  # JSON, both plots, per clip at least the GT and base trajectories
    assert files == sorted(p.relative_to(dist) for p in dist.rglob("*") if p.is_file())
    for f in files:
        assert (serial / f).read_bytes() == (dist / f).read_bytes(), f
    assert "4/4" in err and "2 workers on 1 node(s), 0 tasks run again" in err  # the bar counted clips


def test_chained_sequences_on_ray_match_the_serial_run(local_ray, sequence_dir, tmp_path, capsys):
    """Two inputs (the same recording twice, named apart): one sequence per worker, in parallel."""
    runs = {}
    for name, extra in (("serial", []), ("ray", ["--ray"])):
        out = tmp_path / name
        rc, text, err = _eval([sequence_dir, sequence_dir, "--param", "hop=8", "--json-out", out / "eval.json",
                               "--export-tum", out / "tum", "--no-progress", *extra], capsys)
        assert rc == 0, err
        runs[name] = (out, text)
    (serial, text), (dist, dist_text) = runs["serial"], runs["ray"]
    obj = json.loads((serial / "eval.json").read_text())
    assert [s["n_clips"] for s in obj["sequences"]] == [4, 4] and obj["pooled"]["chained"]["scored"], obj["pooled"]
    assert text == dist_text
    assert (serial / "eval.json").read_text() == (dist / "eval.json").read_text()
    for f in sorted(serial.rglob("odom_*.txt")):
        assert f.read_text() == (dist / f.relative_to(serial)).read_text(), f


class DiesOnce(ClassicalBackbone):
    """The classical backbone, except that the first worker to preprocess a clip while ``marker`` does not exist
    creates it and kills its own process (SIGKILL, as the OOM killer does): a worker lost in the middle of a clip."""

    def __init__(self, marker: str) -> None:
        super().__init__()
        self.marker = marker

    def preprocess(self, images, K):
        try:
            os.close(os.open(self.marker, os.O_CREAT | os.O_EXCL))
        except FileExistsError:
            return super().preprocess(images, K)
        os.kill(os.getpid(), signal.SIGKILL)


@pytest.mark.parametrize("chained", [False, True], ids=["independent", "chained"])
def test_a_worker_killed_mid_clip_is_replaced_and_its_task_run_again(local_ray, sequence_dir, tmp_path, chained):
    options = runner.EvalOptions(clips="sliding", hop=8, progress=False)
    seq = read_asl(sequence_dir)
    if chained:
        evals, online = runner.evaluate_online(seq, make_backbone("classical"), options=options)
    else:
        evals, online = runner.evaluate_sequence(seq, make_backbone("classical"), options=options), None
    job = distributed.Job(str(sequence_dir), seq.name, options, tuple(runner.check_sequence(seq, options=options)),
                          chained=chained)
    ran = distributed.evaluate([job], backbone=functools.partial(DiesOnce, str(tmp_path / "died")),
                               open_sequence=read_asl)
    assert (tmp_path / "died").exists() and len(ran.retried) == 1, ran.retried
    assert "died" in ran.retried[0] and "running it again (1 of 2 retries)" in ran.retried[0]
    assert len(ran.workers) == (2 if not chained else 1) + 1  # the dead worker's replacement
    (res,) = ran.results
    assert res.errors == [] and not ran.interrupted
    assert report.to_json(report.summarise(res.evals, mode="init")) == report.to_json(
        report.summarise(evals, mode="init"))
    if chained:
        assert report.to_json(report.chained_summary(res.online)) == report.to_json(report.chained_summary(online))


def test_a_clip_that_cannot_be_read_is_reported_and_the_others_are_written(local_ray, sequence_dir, tmp_path,
                                                                           capsys):
    broken = assemble(sequence_dir, tmp_path / "broken", skip_image=20)  # in the clips of frames 8-22 and 16-30
    json_out = tmp_path / "eval.json"
    rc, text, err = _eval([broken, "--independent", *HOP, "--json-out", json_out, "--no-progress", "--ray"], capsys)
    assert rc == 2
    obj = json.loads(json_out.read_text())
    assert obj["partial"] is True and obj["n_clips"] == 2, obj.get("errors")
    assert [c["frames"] for c in obj["clips"]] == [[0, 14], [24, 38]]
    assert "frames 8-22" in obj["error"] and "frames 16-30" in obj["error"] and "not a readable PNG" in obj["error"]
    assert "PARTIAL" in text and "frames 16-30" in err


def test_ctrl_c_stops_the_workers_and_returns_what_finished(local_ray, sequence_dir):
    options = runner.EvalOptions(clips="sliding", hop=4, progress=False)  # 7 clips
    seq = read_asl(sequence_dir)
    clips = runner.check_sequence(seq, options=options)

    def interrupt(done: int) -> None:  # Ctrl-C as the first clip comes back
        if done == 1:
            os.kill(os.getpid(), signal.SIGINT)

    job = distributed.Job(str(sequence_dir), seq.name, options, tuple(clips))
    ran = distributed.evaluate([job], backbone=functools.partial(make_backbone, "classical"), open_sequence=read_asl,
                               on_progress=interrupt)
    (res,) = ran.results
    assert ran.interrupted and 1 <= len(res.evals) < len(clips)
    assert res.errors == [f"interrupted: {len(res.evals)} of {len(clips)} clips evaluated"]


def _read_until(proc: subprocess.Popen, pattern: bytes, timeout_s: float) -> bytes:
    """What ``proc`` wrote on stderr up to a match of the regex ``pattern`` (or its exit, or ``timeout_s``)."""
    seen, deadline = b"", time.monotonic() + timeout_s
    with selectors.DefaultSelector() as sel:
        sel.register(proc.stderr, selectors.EVENT_READ)
        while not re.search(pattern, seen) and time.monotonic() < deadline:
            if sel.select(timeout=1.0):
                chunk = os.read(proc.stderr.fileno(), 4096)
                if not chunk:
                    break
                seen += chunk
    return seen


def test_ctrl_c_in_the_terminal_writes_what_finished_marked_partial(local_ray, ray_module, sequence_dir, tmp_path):
    """The command's process group gets SIGINT, as from a terminal; it joins the module's Ray instance by its
    address (HOST:PORT), as a second driver."""
    json_out = tmp_path / "eval.json"
    address = ray_module.get_runtime_context().gcs_address
    proc = subprocess.Popen([sys.executable, "-m", "vi3_ros.cli", "eval", str(sequence_dir), "--independent",
                             "--clips", "sliding", "--param", "hop=2", "--json-out", str(json_out), "--ray", address],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    # the bar counts finished clips and may skip counts when several come back at once
    seen = _read_until(proc, rb" ([1-9]|1[0-3])/14 ", timeout_s=180)
    os.killpg(proc.pid, signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    err = (seen + err).decode()
    assert proc.returncode == 128 + signal.SIGINT, err
    obj = json.loads(json_out.read_text())
    assert obj["partial"] is True and 1 <= obj["n_clips"] < 14, obj.get("errors")
    assert obj["errors"] == [f"{obj['sequence']}: interrupted: {obj['n_clips']} of 14 clips evaluated"]
    assert "PARTIAL" in out.decode() and "Traceback" not in err


def test_without_ray_the_option_says_how_to_install_it(sequence_dir, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` fails, as where it is not installed
    rc, _, err = _eval([sequence_dir, "--ray", "--no-progress"], capsys)
    assert rc == 2 and "pip install ray" in err and "'.[ray]'" in err, err


@pytest.mark.parametrize("args, says", [
    (["--ray-cpus-per-task", "2"], "--ray-cpus-per-task need --ray"),
    (["--ray", "not/an/address"], "put --ray after the inputs"),
    (["--ray", "--device", "cuda"], "needs --ray-gpus-per-task > 0"),
])
def test_ray_options_are_checked_before_anything_runs(ray_module, sequence_dir, capsys, args, says):
    rc, _, err = _eval([sequence_dir, "--no-progress", *args], capsys)
    assert rc == 2 and says in err, err


def test_a_backbone_that_cannot_be_built_on_the_workers_stops_the_run_before_any_clip(local_ray, sequence_dir,
                                                                                        tmp_path, capsys):
    json_out = tmp_path / "eval.json"
    rc, _, err = _eval([sequence_dir, "--backbone", "vggt", "--max-clips", "1", "--json-out", json_out,
                        "--no-progress", "--ray"], capsys)
    assert rc == 2 and "the backbone cannot be built on the Ray worker" in err and "BackboneUnavailable" in err, err
    assert not json_out.exists()
