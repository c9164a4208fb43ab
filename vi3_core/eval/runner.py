"""The evaluation loop: clips of a sequence -> the same ``anchor`` the node runs -> per-clip metrics.

Clips are sampled as in the paper (n = 8 frames, stride 2, start / middle / end of the sequence) or every clip
("sliding"). Each clip goes through ``vi3_core.anchor.anchor`` with the GT-free initialisation (``init_source =
"vi3"``) or the oracle initialisation from ground truth (``"gt"``: GT gravity, v1 and gyro bias, as the paper's
GT-vs-GT-free tables). Ground-truth depth (undistorted image resolution) is resampled onto the backbone's working
grid by nearest neighbour (``metrics.resample_depth``), so predictions are compared at the resolution the model
produced them and no depth value is invented.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from tqdm import tqdm

from vi3_core.anchor import MODES, AnchorOptions, anchor
from vi3_core.backbones.base import Backbone
from vi3_core.dataset.sequence import Sequence, make_clip, sample_clips
from vi3_core.errors import DataError
from vi3_core.eval import metrics
from vi3_core.eval.chained import ChainedMetrics, chained_metrics
from vi3_core.eval.clip_eval import ClipEval
from vi3_core.init import InitOptions, oracle_init
from vi3_core.init.oracle import gt_init_state
from vi3_core.online import OnlineEstimator, OnlineOptions
from vi3_core.types import AnchorResult, Clip, Geometry, InitResult

INIT_SOURCES = ("vi3", "gt")
CLIP_SAMPLING = ("paper", "sliding")

#: The supplementary tables' initialisation ablations, as ``InitOptions`` overrides of the paper's defaults.
ABLATIONS: dict[str, dict] = {
    "error-model fit (default)": {},
    "paper Eq. S (TLS, all-pairs, consensus)": {"scale_solver": "tls"},
    "OLS scale": {"scale_solver": "ols"},
    "first-pair v1": {"scale_solver": "tls", "v1_method": "first_pair"},
    "no gravity consensus": {"scale_solver": "tls", "use_consensus": False},
}


@dataclass(frozen=True)
class EvalOptions:
    """Options of ``evaluate_sequence``.

    mode: anchoring mode of the VI3 column ("init" | "cond" | "ttr"); with "cond"/"ttr" the fast init result
        (which ``anchor`` reports before refining) is evaluated too, as the "init" column.
    init_source: "vi3" (GT-free, the default) or "gt" (oracle initialisation from ground truth).
    clips: "paper" (start / middle / end) or "sliding" (every ``hop`` frames); n, stride: frames per clip and
        frame stride; max_clips: keep at most this many clips (evenly spread), None for all.
    """

    mode: str = "init"
    init_source: str = "vi3"
    clips: str = "paper"
    n: int = 8
    stride: int = 2
    hop: int | None = None
    max_clips: int | None = None
    anchor_options: AnchorOptions | None = None
    init_options: InitOptions | None = None
    progress: bool = True

    def __post_init__(self) -> None:
        for name, value, allowed in (("mode", self.mode, MODES), ("init_source", self.init_source, INIT_SOURCES),
                                     ("clips", self.clips, CLIP_SAMPLING)):
            if value not in allowed:
                raise ValueError(f"EvalOptions.{name} must be one of {', '.join(allowed)}; got {value!r}")


def _column_metrics(geometry: Geometry, T_gt: np.ndarray, depth_gt: np.ndarray | None) -> metrics.GeometryMetrics:
    return metrics.geometry_metrics(geometry.T_wc, T_gt, geometry.depth if depth_gt is not None else None, depth_gt)


def evaluate_clip(clip: Clip, backbone: Backbone, *, options: EvalOptions, indices: np.ndarray | None = None,
                  init: Callable[[Geometry], InitResult] | None = None) -> ClipEval:
    """Anchor ``clip`` (which must carry ground truth) and compute every metric of the paper on it. ``init``
    (with ``init_source`` "vi3") builds the initialisation from the base geometry (``vi3_core.online``)."""
    if clip.gt is None:
        raise DataError(f"evaluate_clip: the clip at t = {clip.stamps[0]:.6f}..{clip.stamps[-1]:.6f} s has no ground "
                        "truth (the GT track does not cover it); evaluation needs GT poses and velocities")
    if options.init_source == "gt":
        init = lambda base: oracle_init(clip, base)  # scales anchor's own base prediction: one forward pass
    if hasattr(backbone, "bind"):  # the ground-truth pose instrument predicts from the clip's ground truth
        backbone.bind(clip)
    fast: list[AnchorResult] = []
    result = anchor(clip, backbone, mode=options.mode, options=options.anchor_options,
                    init_options=options.init_options, init=init,
                    on_init=fast.append if options.mode != "init" else None)
    T_gt = metrics.gt_camera_poses(clip.gt, clip.T_BC)
    g_b1, _, _ = gt_init_state(clip.gt)
    down_c1 = clip.T_BC[:3, :3].T @ g_b1 / np.linalg.norm(g_b1)

    depth_gt = None
    if clip.gt.depth is not None:
        depth_gt = metrics.resample_depth(clip.gt.depth, clip.K, result.base.K[0],
                                          result.base.depth.shape[1:])
    columns = {"base": _column_metrics(result.base, T_gt, depth_gt)}
    if result.init.ok:
        if fast:
            columns["init"] = _column_metrics(fast[0].geometry, T_gt, depth_gt)
        columns[result.mode] = _column_metrics(result.geometry, T_gt, depth_gt)
    return ClipEval(indices=np.arange(clip.n) if indices is None else np.asarray(indices), stamps=clip.stamps,
                    status=result.init.status.value, reason=result.init.reason, mode=result.mode, T_gt=T_gt,
                    down_c1=down_c1, result=result, fast=fast[0] if fast and result.init.ok else None,
                    columns=columns,
                    init_metrics=metrics.init_metrics(result.init, clip.gt))


def clip_indices(n_frames: int, *, options: EvalOptions) -> list[np.ndarray]:
    """Frame indices of the clips to evaluate (``sample_clips``), thinned evenly to ``max_clips``."""
    clips = sample_clips(n_frames, n=options.n, stride=options.stride, mode=options.clips, hop=options.hop)
    if options.max_clips is not None and len(clips) > options.max_clips:
        keep = np.unique(np.linspace(0, len(clips) - 1, options.max_clips).round().astype(int))
        clips = [clips[i] for i in keep]
    return clips


def evaluate_sequence(seq: Sequence, backbone: Backbone, *, options: EvalOptions | None = None) -> list[ClipEval]:
    """Evaluate every sampled clip of ``seq`` (which must have ground truth), with a progress bar over clips."""
    options = options or EvalOptions()
    if seq.gt is None:
        raise DataError(f"sequence {seq.name!r} has no ground truth; evaluation needs GT poses and velocities")
    out = []
    for idx in tqdm(clip_indices(len(seq.stamps), options=options), desc=f"eval {seq.name}", unit="clip",
                    disable=not options.progress):
        out.append(evaluate_clip(make_clip(seq, idx, with_images=backbone.needs_images), backbone, options=options,
                                 indices=idx))
    return out


def ablate(seq: Sequence, backbone: Backbone, *, options: EvalOptions | None = None) -> dict[str, list[ClipEval]]:
    """The supplementary initialisation ablations (``ABLATIONS``): one ``evaluate_sequence`` per variant, in
    ``init`` mode with the GT-free initialisation (the variants are its options), each variant's ``InitOptions``
    derived from ``options.init_options`` (or the defaults)."""
    options = options or EvalOptions()
    base = options.init_options or InitOptions()
    return {name: evaluate_sequence(seq, backbone, options=dataclasses.replace(
                options, mode="init", init_source="vi3", init_options=dataclasses.replace(base, **overrides)))
            for name, overrides in ABLATIONS.items()}


@dataclass
class OnlineRun:
    """The chained run of a sequence: stamps [N] s, T_OB [N,4,4] the odom trajectory, T_WB [N,4,4] GT body
    poses at the same stamps, decisions: the estimator's description of each clip; scale_err,
    independent_scale_err: [n_clips] |Scale (Traj.) - 1| of each clip chained and of its own GT-free
    initialisation (NaN: no value); metrics (None with < 2 poses)."""

    stamps: np.ndarray
    T_OB: np.ndarray
    T_WB: np.ndarray
    decisions: list[str] = field(default_factory=list)
    scale_err: np.ndarray = field(default_factory=lambda: np.zeros(0))
    independent_scale_err: np.ndarray = field(default_factory=lambda: np.zeros(0))
    metrics: ChainedMetrics | None = None


def evaluate_online(seq: Sequence, backbone: Backbone, *, options: EvalOptions | None = None,
                    online_options: OnlineOptions | None = None,
                    clips: list[np.ndarray] | None = None) -> tuple[list[ClipEval], OnlineRun]:
    """``evaluate_sequence`` with the metric state carried across clips (``vi3_core.online``, GT-free): each clip's
    initialisation from the stream's priors, and the clips chained into one odom trajectory, scored against GT.
    ``clips`` overrides the sampled frame indices (a test leaves a gap in the images)."""
    options = options or EvalOptions()
    if options.init_source != "vi3":
        raise ValueError("chained evaluation is GT-free: use init_source 'vi3' (or the independent evaluation)")
    if seq.gt is None:
        raise DataError(f"sequence {seq.name!r} has no ground truth; evaluation needs GT poses and velocities")
    est = OnlineEstimator(options=online_options, init_options=options.init_options)
    evals, decisions, scale_err, independent = [], [], [], []
    for idx in tqdm(clip_indices(len(seq.stamps), options=options) if clips is None else clips,
                    desc=f"eval {seq.name} (chained)", unit="clip", disable=not options.progress):
        # IMU before the clip over the longest gap the window bridges, as the node's clip buffer keeps it.
        clip = make_clip(seq, idx, history_s=est.options.max_bridge_s, with_images=backbone.needs_images)
        ev = evaluate_clip(clip, backbone, options=options, indices=idx,
                           init=lambda base, clip=clip: est.initialise(clip, base))
        est.update(clip, ev.result)
        decisions.append(est.last.describe())
        evals.append(ev)
        diag = ev.result.init.diagnostics
        base_scale = ev.columns["base"].scale_traj  # linear in the scale: the free init's = base * its scale
        independent.append(abs(base_scale * diag["free_scale"] - 1.0) if diag["free_status"] == "ok" else np.nan)
        scale_err.append(abs(ev.columns[ev.mode].scale_traj - 1.0) if ev.mode in ev.columns else np.nan)
    traj = est.trajectory
    T_WB = seq.gt.at(traj.stamps).T_WB if len(traj.stamps) else np.zeros((0, 4, 4))
    run = OnlineRun(traj.stamps, traj.T_OB, T_WB, decisions, np.array(scale_err), np.array(independent))
    if len(traj.stamps) >= 2:
        run.metrics = chained_metrics(traj.T_OB, T_WB, resets=len(traj.resets), scale_err=run.scale_err,
                                      independent_scale_err=run.independent_scale_err)
    return evals, run
