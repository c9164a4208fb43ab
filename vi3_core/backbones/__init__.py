"""Backbone registry: ``make_backbone(name, ...)`` for classical | vggt | vggt_omega | pi3 | pi3x | da3."""

from __future__ import annotations

import importlib

import torch

from vi3_core.backbones.base import Backbone
from vi3_core.errors import DeviceUnavailable

BACKBONES: dict[str, str] = {
    "classical": "vi3_core.backbones.classical:ClassicalBackbone",
    "vggt": "vi3_core.backbones.vggt:VGGTBackbone",
    "vggt_omega": "vi3_core.backbones.vggt_omega:VGGTOmegaBackbone",
    "pi3": "vi3_core.backbones.pi3:Pi3Backbone",
    "pi3x": "vi3_core.backbones.pi3:Pi3XBackbone",
    "da3": "vi3_core.backbones.da3:DA3Backbone",
}


def backbone_class(name: str) -> type[Backbone]:
    """The class of backbone ``name`` (imports its adapter module only; upstream packages load on instantiation)."""
    if name not in BACKBONES:
        raise ValueError(f"unknown backbone {name!r}; choose one of {', '.join(BACKBONES)}")
    module, cls = BACKBONES[name].split(":")
    return getattr(importlib.import_module(module), cls)


def backbones_with(capability: str) -> list[str]:
    """Names of the backbones that have ``capability`` (``vi3_core.backbones.base.CAP_*``), in registry order."""
    return [name for name in BACKBONES if capability in backbone_class(name).capabilities]


def check_device(device: str) -> None:
    """DeviceUnavailable naming ``device`` when torch cannot run on it here (malformed, no CUDA/MPS, no such GPU)."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as err:
        raise DeviceUnavailable(f"device {device!r} is not a torch device (e.g. cpu, cuda, cuda:1): {err}") from None
    if dev.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise DeviceUnavailable(f"device {device!r}: this torch ({torch.__version__}) sees no CUDA GPU "
                                    "(torch.cuda.is_available() is False); use cpu")
        if dev.index is not None and dev.index >= count:
            raise DeviceUnavailable(f"device {device!r}: there are only {count} CUDA GPU(s) (cuda:0..{count - 1})")
    elif dev.type == "mps" and not torch.backends.mps.is_available():
        raise DeviceUnavailable(f"device {device!r}: MPS is not available to this torch; use cpu")


def make_backbone(name: str, *, device: str = "cpu", dtype: torch.dtype = torch.float32,
                  checkpoint: str | None = None, **options) -> Backbone:
    """Instantiate a backbone by name on ``device`` (checked first: ``check_device``). Adapters raise
    ``BackboneUnavailable`` naming the install command and the expected checkpoint location when their upstream
    package or weights are missing; there is never a silent fallback to another model."""
    cls = backbone_class(name)
    check_device(device)
    kwargs = dict(device=device, dtype=dtype, **options)
    if checkpoint is not None:
        kwargs["checkpoint"] = checkpoint
    return cls(**kwargs)
