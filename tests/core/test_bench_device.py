"""``vi3 bench backbone|ttr`` options (--dtype, --random-init, --resolution, --device), their errors, the keys of
the TTR benchmark's JSON, the device clock, and, where an upstream 3DFM package imports, a random-weight run of
the backbone benchmark at a tiny resolution. No timing is asserted: speed is read from the JSON, never tested."""

from __future__ import annotations

import argparse
import json
import math

import pytest
import torch
from test_backbone_adapters import ADAPTERS, _importable

from vi3_core.anchor.bench import bench_ttr
from vi3_core.backbones.bench import bench_backbone
from vi3_core.backbones.bench_device import DTYPES, DeviceClock, build_bench_backbone, foundation_models
from vi3_ros import cli


def _bench(capsys, *argv: str) -> tuple[int, dict]:
    rc = cli.main(["bench", *argv, "--json"])
    return rc, json.loads(capsys.readouterr().out)


def _args(**given) -> argparse.Namespace:
    """The bench options as the CLI parses them, with ``given`` replacing the defaults."""
    args = cli.build_parser().parse_args(["bench", "backbone"])
    return argparse.Namespace(**{**vars(args), **given})


@pytest.mark.parametrize("option", [["--random-init"], ["--resolution", "112"], ["--dtype", "bf16"]])
@pytest.mark.parametrize("bench", ["backbone", "ttr"])
def test_weight_options_are_refused_for_classical(capsys, bench, option):
    rc, out = _bench(capsys, bench, "--backbone", "classical", *option)
    assert rc == 2 and out["bench"] == bench
    assert option[0] in out["error"] and "'classical'" in out["error"] and "vggt" in out["error"]


def test_dtype_is_validated(capsys):
    for name in DTYPES:  # the CLI accepts every dtype the benchmarks map
        assert cli.build_parser().parse_args(["bench", "ttr", "--dtype", name]).dtype == name
    with pytest.raises(SystemExit) as exc:
        cli.main(["bench", "backbone", "--dtype", "fp64"])
    assert exc.value.code == 2 and "invalid choice: 'fp64'" in capsys.readouterr().err
    with pytest.raises(ValueError, match="dtype 'float64': choose one of fp32, bf16, fp16"):
        build_bench_backbone(_args(dtype="float64"))


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
@pytest.mark.parametrize("bench", ["backbone", "ttr"])
def test_cuda_without_a_gpu_exits_2_naming_the_device(capsys, bench):
    rc, out = _bench(capsys, bench, "--device", "cuda")
    assert rc == 2 and "device 'cuda'" in out["error"] and "sees no CUDA GPU" in out["error"]


def test_foundation_models_are_the_adapters():
    assert foundation_models() == list(ADAPTERS)


@pytest.mark.slow
def test_bench_ttr_reports_the_paper_table_columns(cache_dir, monkeypatch):
    monkeypatch.setenv("VI3_CACHE", str(cache_dir))
    out = bench_ttr(_args(bench="ttr", repeats=3))
    assert (out["backbone"], out["device"], out["dtype"], out["random_init"], out["init"]) == \
        ("classical", "cpu", "fp32", False, "gt_free")
    assert out["steps"] == 3 and "peak_gpu_mem_mb" not in out
    # The GT-free initialisation must claim the bench clip, or the benchmark measures no step at all.
    assert (out["init_status"], out["mode"]) == ("ok", "ttr")
    assert out["ms_per_iter"] > 0 and 0 < out["ttr_s"] < out["total_s"] and 0 < out["backbone_s"] < out["total_s"]
    assert out["paper_total_s"] == pytest.approx(out["init_ms"] / 1e3 + 160 * out["ms_per_iter"] / 1e3)
    assert out["init_ms"] > 0


def test_device_clock_times_a_lap_and_reports_memory_only_on_cuda():
    clock = DeviceClock("cpu")
    with clock.lap() as lap:
        assert math.isnan(lap.wall_s)
        torch.randn(256, 256) @ torch.randn(256, 256)
    assert lap.wall_s > 0 and lap.cpu_s >= 0 and clock.memory() == {}


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_device_clock_peak_memory_on_cuda():
    clock = DeviceClock("cuda")
    base = clock.memory()["peak_gpu_mem_mb"]
    with clock.lap():
        x = torch.empty(64 * 2**20, dtype=torch.uint8, device="cuda")
    assert clock.memory()["peak_gpu_mem_mb"] >= base + 64
    del x


@pytest.mark.parametrize("name", sorted(ADAPTERS))
def test_bench_backbone_random_init_bf16_at_a_tiny_resolution(cache_dir, monkeypatch, name):
    module, hint, options = ADAPTERS[name]
    if not _importable(module):
        pytest.skip(f"upstream {module!r} for backbone {name!r} is not importable ({hint} not installed)")
    monkeypatch.setenv("VI3_CACHE", str(cache_dir))
    torch.manual_seed(0)
    out = bench_backbone(_args(backbone=name, random_init=True, resolution=options["resolution"], dtype="bf16",
                               repeats=1))  # bf16: the trunk under autocast, heads in float32, as on a GPU
    assert (out["backbone"], out["dtype"], out["random_init"], out["frames"]) == (name, "bf16", True, 8)
    assert out["median_s"] > 0 and min(out["working_resolution"]) >= 14
