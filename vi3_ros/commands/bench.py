"""``vi3 bench NAME``: speed and memory targets, printed as one JSON object per benchmark.

Each benchmark is a ROS-free function ``fn(args) -> dict`` in the module that owns the code it measures.
"""

from __future__ import annotations

import argparse
import importlib

BENCHES: dict[str, str] = {
    "init": "vi3_core.init.bench:bench_init",
    "pointcloud": "msg_adapters.bench:bench_pointcloud",
    "backbone": "vi3_core.backbones.bench:bench_backbone",
    "tracker": "vi3_core.backbones.classical.bench:bench_tracker",
    "ttr": "vi3_core.anchor.bench:bench_ttr",
    "replay": "vi3_ros.replay_bench:bench_replay",
    "pipeline": "vi3_ros.replay_bench:bench_pipeline",
    "soak": "vi3_ros.replay_bench:bench_soak",
}
#: Not part of ``vi3 bench all`` (``make bench``): half an hour of replay.
LONG = ("soak",)


def _load(name: str):
    module, fn = BENCHES[name].split(":")
    return getattr(importlib.import_module(module), fn)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="run a benchmark and print JSON")
    p.add_argument("name", choices=[*BENCHES, "all"])
    p.add_argument("--json", action="store_true", help="print only the JSON object(s)")
    p.add_argument("--repeats", type=int, default=None, help="timed repetitions (default: per benchmark)")
    p.add_argument("--backbone", default="classical", help="backbone for backbone/ttr/replay benchmarks")
    p.add_argument("--device", default="cpu", help="torch device for backbone/ttr/replay (cpu, cuda, cuda:1, mps)")
    p.add_argument("--dtype", default="fp32", choices=["fp32", "bf16", "fp16"],
                   help="backbone/ttr benchmarks: precision of a 3DFM's transformer trunk (autocast; weights and "
                   "heads stay float32); torch runs both bf16 and fp16 autocast on CPU too")
    p.add_argument("--random-init", action="store_true",
                   help="backbone/ttr benchmarks: a 3DFM's architecture with random weights (timing without a "
                   "checkpoint); not for classical, which has no weights")
    p.add_argument("--resolution", type=int, default=None, metavar="N",
                   help="backbone/ttr benchmarks: a 3DFM's input resolution option (width for vggt, side of the pixel "
                   "budget for vggt_omega, pixels for pi3/pi3x, longest side for da3; docs/backbones.md); default "
                   "the adapter's")
    p.add_argument("--input", default=None, help="input sequence for the replay and pipeline benchmarks")
    p.add_argument("--seconds", type=float, default=None, help="length of the generated replay input (default 20)")
    p.add_argument("--minutes", type=float, default=None, help="soak benchmark: minutes of bag time to replay the "
                   "input for, in passes (default 30)")
    p.add_argument("--realtime", action="store_true", help="replay benchmark: at the recorded rate into the node's "
                   "worker thread (vi3 replay --realtime)")
    p.add_argument("--backbone-delay", type=float, default=None, metavar="S",
                   help="replay benchmark: S seconds added to every clip (parameter backbone_delay)")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="replay benchmark: any node parameter")
    p.add_argument("--threads", type=_threads, default=0, metavar="N",
                   help="torch intra-op threads, OpenCV's pool and the classical backbone's plane-sweep threads, set "
                   "once before the benchmarks (the node parameter threads); 0 (default): min(2, CPUs this process "
                   "may use)")
    p.set_defaults(func=run)


def _threads(text: str) -> int:
    n = int(text)
    if n < 0:
        raise argparse.ArgumentTypeError(f"--threads must be >= 0 (0: automatic), got {n}")
    return n


def run(args: argparse.Namespace) -> int:
    """Each benchmark's JSON; a benchmark that cannot run here (missing package or checkpoint, no such device, an
    option its backbone does not take) prints ``{"bench", "error"}`` and the exit status is 2."""
    from vi3_core.errors import Vi3Error
    from vi3_core.eval.report import to_json  # strict JSON: a NaN timing or ratio prints as null
    from vi3_core.threads import use_threads

    use_threads(args.threads)
    args.param = [f"threads={args.threads}", *args.param]  # the replay's pipeline sets it again from its parameters

    names = [n for n in BENCHES if n not in LONG] if args.name == "all" else [args.name]
    status = 0
    for name in names:
        try:
            result = {"bench": name, **_load(name)(args)}
        except (ImportError, AttributeError) as exc:
            result, status = {"bench": name, "error": f"not available: {exc}"}, 2
        except (Vi3Error, ValueError) as exc:
            result, status = {"bench": name, "error": str(exc)}, 2
        print(to_json(result))
    return status
