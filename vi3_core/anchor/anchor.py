"""``anchor``: one clip through a backbone, the GT-free initialisation and a metric anchoring mode. The node, the
replay tool, the evaluation and the benchmarks all call this one function."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from vi3_core.anchor.options import MODES, AnchorOptions
from vi3_core.anchor.ttr import refine
from vi3_core.backbones.base import CAP_COND_INTRINSICS, CAP_COND_POSE, CAP_TTR, Backbone, Condition
from vi3_core.errors import ModeNotSupported
from vi3_core.init import InitOptions, initialise_clip
from vi3_core.init.gravity_seeds import geocalib_available, geocalib_seed
from vi3_core.types import AnchorResult, Clip, Geometry, InitResult

_REQUIRED = {"cond": CAP_COND_POSE, "ttr": CAP_TTR}


def check_mode(backbone: Backbone, mode: str) -> None:
    """Raise ModeNotSupported (or ValueError for an unknown mode) before any work is done."""
    if mode not in MODES:
        raise ValueError(f"unknown anchoring mode {mode!r}; choose one of {', '.join(MODES)}")
    need = _REQUIRED.get(mode)
    if need and need not in backbone.capabilities:
        from vi3_core.backbones import backbones_with  # the registry imports every adapter module: only here

        raise ModeNotSupported(f"backbone {backbone.name!r} cannot do mode {mode!r} (it lacks {need!r}; it "
                               f"supports: {', '.join(sorted(backbone.capabilities)) or 'init only'}); backbones "
                               f"that can: {', '.join(backbones_with(need)) or 'none'}")


def anchor(clip: Clip, backbone: Backbone, *, mode: str = "init", options: AnchorOptions | None = None,
           init_options: InitOptions | None = None,
           init: InitResult | Callable[[Geometry], InitResult] | None = None,
           on_init: Callable[[AnchorResult], None] | None = None) -> AnchorResult:
    """Metric geometry for one clip.

    mode "init": the initialisation's scale applied to translation and depth (no gradient steps);
    "cond": the IMU target poses (and intrinsics where supported) fed to a conditioning-capable backbone;
    "ttr": test-time refinement. ``init`` overrides the GT-free initialisation (e.g. ``oracle_init``); a callable
    receives the base geometry and returns the InitResult (``vi3_core.online`` builds it from the stream's priors).
    ``on_init`` receives the fast init-mode result before any refinement starts (the node publishes it).
    A clip whose initialisation is not ok is returned unscaled with mode "none" and the reason in ``status``;
    bad data never raises. An unknown or unsupported mode raises before the backbone runs.
    """
    check_mode(backbone, mode)
    options = options or AnchorOptions()
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    inputs = backbone.preprocess(clip.images, clip.K)
    base_pred = backbone.predict_inputs(inputs)
    base = base_pred.geometry()
    timings["backbone_s"] = time.perf_counter() - t0

    if callable(init):
        t1 = time.perf_counter()
        init = init(base)
        timings["init_s"] = time.perf_counter() - t1
    elif init is None:
        t1 = time.perf_counter()
        seeds = None
        if options.geocalib and geocalib_available():
            seeds = {"geocalib": geocalib_seed(clip.images[0], clip.T_BC, (init_options or InitOptions()).gravity_norm)}
        init = initialise_clip(clip, base, options=init_options, seeds=seeds)
        timings["init_s"] = time.perf_counter() - t1

    if not init.ok:
        result = AnchorResult(geometry=base, base=base, init=init, mode="none", alpha=float("nan"),
                              timings=timings, status=f"{init.status.value}: {init.reason}")
        if on_init is not None:
            on_init(result)
        return result

    fast = AnchorResult(geometry=base.scaled(init.scale), base=base, init=init, mode="init", alpha=init.scale,
                        target=init.target, timings=dict(timings), status="ok")
    fast.geometry.metric = True
    if on_init is not None:
        on_init(fast)
    if mode == "init":
        return fast

    t2 = time.perf_counter()
    if mode == "cond":
        K = inputs.K.detach().double().cpu().numpy() if CAP_COND_INTRINSICS in backbone.capabilities else None
        geometry = backbone.predict_inputs(inputs, Condition(T_wc=init.target.T_wc, K=K)).geometry()
        geometry.metric = True
        timings["cond_s"] = time.perf_counter() - t2
        return AnchorResult(geometry=geometry, base=base, init=init, mode="cond", alpha=init.scale, target=init.target,
                            timings=timings, status="ok")

    ttr = refine(backbone, inputs, base_pred, init.target, options)
    timings["ttr_s"] = time.perf_counter() - t2
    timings["ttr_ms_per_iter"] = float(np.median(ttr.step_ms)) if options.ttr_steps else 0.0
    return AnchorResult(geometry=ttr.geometry, base=base, init=init, mode="ttr", alpha=ttr.alpha, target=init.target,
                        losses=ttr.losses, alphas=ttr.alphas, timings=timings, status="ok")
