"""Backbone registry: ``make_backbone(name, ...)`` for classical | vggt | vggt_omega | pi3 | pi3x | da3."""

from __future__ import annotations

import importlib

import torch

from vi3_core.backbones.base import Backbone

BACKBONES: dict[str, str] = {
    "classical": "vi3_core.backbones.classical:ClassicalBackbone",
    "vggt": "vi3_core.backbones.vggt:VGGTBackbone",
    "vggt_omega": "vi3_core.backbones.vggt_omega:VGGTOmegaBackbone",
    "pi3": "vi3_core.backbones.pi3:Pi3Backbone",
    "pi3x": "vi3_core.backbones.pi3:Pi3XBackbone",
    "da3": "vi3_core.backbones.da3:DA3Backbone",
}


def make_backbone(name: str, *, device: str = "cpu", dtype: torch.dtype = torch.float32,
                  checkpoint: str | None = None, **options) -> Backbone:
    """Instantiate a backbone by name. Adapters raise ``BackboneUnavailable`` naming the install command
    and the expected checkpoint location when their upstream package or weights are missing; there is
    never a silent fallback to another model."""
    if name not in BACKBONES:
        raise ValueError(f"unknown backbone {name!r}; choose one of {', '.join(BACKBONES)}")
    module, cls = BACKBONES[name].split(":")
    kwargs = dict(device=device, dtype=dtype, **options)
    if checkpoint is not None:
        kwargs["checkpoint"] = checkpoint
    return getattr(importlib.import_module(module), cls)(**kwargs)
