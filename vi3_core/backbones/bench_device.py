"""What ``vi3 bench backbone`` and ``vi3 bench ttr`` share: the benchmarked backbone built from the bench options
(``--backbone --device --dtype --random-init --resolution``) with the JSON fields that describe it, and a clock
that synchronises the device before every reading and reports the peak memory torch allocated on a CUDA device."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from dataclasses import dataclass

import torch

from vi3_core.backbones import BACKBONES, backbone_class, make_backbone
from vi3_core.backbones._hub import UpstreamBackbone
from vi3_core.backbones.base import Backbone

#: ``--dtype`` names -> the precision of the 3DFM transformer trunks (autocast; weights and heads stay float32).
DTYPES: dict[str, torch.dtype] = {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}


def foundation_models() -> list[str]:
    """Names of the 3DFM adapters (the backbones with network weights), in registry order."""
    return [name for name in BACKBONES if issubclass(backbone_class(name), UpstreamBackbone)]


def build_bench_backbone(args) -> tuple[Backbone, dict]:
    """The backbone of ``args`` (``backbone``, ``device``, ``dtype`` name of ``DTYPES``, ``random_init``,
    ``resolution`` or None for the adapter's default) from ``make_backbone``, and the JSON fields backbone, device,
    dtype, random_init.

    Raises ValueError for a dtype name outside ``DTYPES``, and for ``random_init``, ``resolution`` or a dtype other
    than fp32 on a backbone that is not a 3DFM (``classical`` has no weights, no model input resolution and no
    transformer trunk; cast to bfloat16 its TTR fails in ``torch.linalg.inv``); ``DeviceUnavailable`` and
    ``BackboneUnavailable`` from ``make_backbone``."""
    if args.dtype not in DTYPES:
        raise ValueError(f"dtype {args.dtype!r}: choose one of {', '.join(DTYPES)}")
    if not issubclass(backbone_class(args.backbone), UpstreamBackbone):
        for flag, given in (("--random-init", args.random_init), ("--resolution", args.resolution is not None),
                            (f"--dtype {args.dtype}", args.dtype != "fp32")):
            if given:
                raise ValueError(f"{flag} applies to the 3D foundation models ({', '.join(foundation_models())}); "
                                 f"backbone {args.backbone!r} has no network weights, model input resolution or "
                                 "transformer trunk (it runs in float32)")
    options = {"random_init": True} if args.random_init else {}
    if args.resolution is not None:
        options["resolution"] = args.resolution
    backbone = make_backbone(args.backbone, device=args.device, dtype=DTYPES[args.dtype], **options)
    return backbone, {"backbone": args.backbone, "device": str(args.device), "dtype": args.dtype,
                      "random_init": bool(args.random_init)}


@dataclass
class Lap:
    """Wall and process-CPU seconds of one ``DeviceClock.lap`` (NaN until the lap ends)."""

    wall_s: float = float("nan")
    cpu_s: float = float("nan")


class DeviceClock:
    """Times code that queues asynchronous work on ``device``: each lap synchronises the device (CUDA, MPS) before
    it starts and before it stops, so the lap holds the device's work and not only its queueing. On CUDA it also
    tracks the peak memory torch allocates on the device from the clock's creation (memory held then, such as the
    model's weights, is part of the peak)."""

    def __init__(self, device: str | torch.device) -> None:
        self.device = torch.device(device)
        if self.device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(self.device)

    def synchronize(self) -> None:
        """Wait for the work queued on the device."""
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        elif self.device.type == "mps":
            torch.mps.synchronize()

    @contextlib.contextmanager
    def lap(self) -> Iterator[Lap]:
        """``with clock.lap() as lap: ...``: ``lap.wall_s`` and ``lap.cpu_s`` are set when the block ends."""
        lap = Lap()
        self.synchronize()
        t0, c0 = time.perf_counter(), time.process_time()
        yield lap
        self.synchronize()
        lap.wall_s, lap.cpu_s = time.perf_counter() - t0, time.process_time() - c0

    def memory(self) -> dict[str, float]:
        """``{"peak_gpu_mem_mb": MiB}`` on CUDA (``torch.cuda.max_memory_allocated``), empty on other devices."""
        if self.device.type != "cuda":
            return {}
        return {"peak_gpu_mem_mb": round(torch.cuda.max_memory_allocated(self.device) / 2**20, 1)}
