"""The evaluation loop: clips of a sequence -> the node's ``StreamEstimator`` -> per-clip metrics.

Clips are sampled as in the paper (8 frames, stride 2, start / middle / end of the sequence) or every clip
("sliding"). Each clip goes through the same ``vi3_core.online.StreamEstimator`` the node runs: chained
(``evaluate_online``, the node's default), or every clip on its own (``evaluate_sequence``) with the GT-free
initialisation (``init_source = "vi3"``) or the oracle initialisation from ground truth (``"gt"``: GT gravity, v1
and gyro bias, as the paper's GT-vs-GT-free tables). Ground-truth depth (undistorted image resolution) is resampled
onto the backbone's working grid by nearest neighbour (``metrics.resample_depth``), so predictions are compared at the
resolution the model produced them and no depth value is invented.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from tqdm import tqdm

from vi3_core.anchor import AnchorOptions
from vi3_core.backbones.base import Backbone
from vi3_core.dataset.sequence import Sequence, gt_camera_poses, make_clip, sample_clips
from vi3_core.errors import DataError, Vi3Error
from vi3_core.eval import metrics
from vi3_core.eval.chained import ChainedMetrics, chained_metrics, gt_path_length
from vi3_core.eval.claims import scale_error
from vi3_core.eval.clip_eval import ClipEval
from vi3_core.eval.coverage import Coverage, coverage, motion_start
from vi3_core.eval.links import ScoredLink, scored_links
from vi3_core.init import InitOptions
from vi3_core.init.oracle import gt_init_state
from vi3_core.online import OnlineDecision, OnlineOptions, StreamEstimator, StreamOptions
from vi3_core.online.calibration import CalibrationOptions, RigEstimate
from vi3_core.types import CLIP_LENGTH, CLIP_STRIDE, Clip, Geometry

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
    """Options of ``evaluate_sequence`` / ``evaluate_online``.

    stream_options: the stream's own options (``StreamOptions``: the anchoring mode of the VI3 column, with
        "cond"/"ttr" the fast init result, which ``anchor`` reports before refining, evaluated too as the "init"
        column; init_source "vi3", GT-free, or "gt", the oracle from ground truth; all_depth: every frame's depth
        predicted, the depth metrics then cover every frame, else the frames the stream reads; the camera's
        rolling_shutter_readout); its ``online`` is set by ``stream``.
    clips: "paper" (start / middle / end) or "sliding" (every ``hop`` frames); clip_length, stride, hop: frames per
        clip, frame stride and frames between sliding clips (None: back to back), as the node's parameters of the same
        names; max_clips: keep at most this many clips (evenly spread), None for all.
    anchor_options, init_options, online_options, calibration_options: the stream's settings (None: the defaults).
    """

    stream_options: StreamOptions = field(default_factory=lambda: StreamOptions(online=False))
    clips: str = "paper"
    clip_length: int = CLIP_LENGTH
    stride: int = CLIP_STRIDE
    hop: int | None = None
    max_clips: int | None = None
    anchor_options: AnchorOptions | None = None
    init_options: InitOptions | None = None
    online_options: OnlineOptions | None = None
    calibration_options: CalibrationOptions | None = None
    progress: bool = True

    def __post_init__(self) -> None:
        if self.clips not in CLIP_SAMPLING:
            raise ValueError(f"EvalOptions.clips must be one of {', '.join(CLIP_SAMPLING)}; got {self.clips!r}")

    def stream(self, backbone: Backbone, *, online: bool) -> StreamEstimator:
        """The stream estimator these options describe (``online``: chained, else every clip on its own)."""
        return StreamEstimator(backbone, options=dataclasses.replace(self.stream_options, online=online),
                               online=self.online_options, init=self.init_options, anchor=self.anchor_options,
                               calibration=self.calibration_options)


def _column_metrics(geometry: Geometry, T_gt: np.ndarray, depth_gt: np.ndarray | None) -> metrics.GeometryMetrics:
    return metrics.geometry_metrics(geometry.T_wc, T_gt, geometry.depth if depth_gt is not None else None, depth_gt)


def evaluate_clip(clip: Clip, stream: StreamEstimator, *, indices: np.ndarray | None = None) -> ClipEval:
    """Run ``clip`` (which must carry ground truth) through ``stream`` and compute every metric of the paper on it."""
    if clip.gt is None:
        raise DataError(f"evaluate_clip: the clip at t = {clip.stamps[0]:.6f}..{clip.stamps[-1]:.6f} s has no ground "
                        "truth (the GT track does not cover it); evaluation needs GT poses and velocities")
    outcome = stream.process(clip)
    if not np.array_equal(outcome.clip.stamps, clip.stamps):  # the stream put shared frames in place of its first
        indices = None
    clip = outcome.clip  # with the rig's self-calibration applied
    result, init = outcome.result, outcome.init
    T_gt = gt_camera_poses(clip.gt, clip.T_BC)
    g_b1, _, _ = gt_init_state(clip.gt)
    down_c1 = clip.T_BC[:3, :3].T @ g_b1 / np.linalg.norm(g_b1)
    columns = {}
    if result is not None:
        depth_gt = None
        if clip.gt.depth is not None:
            depth_gt = metrics.resample_depth(clip.gt.depth, clip.K, result.base.K[0], result.base.depth.shape[1:])
        columns["base"] = _column_metrics(result.base, T_gt, depth_gt)
        if init.ok:
            if outcome.fast is not None:
                columns["init"] = _column_metrics(outcome.fast.geometry, T_gt, depth_gt)
            columns[result.mode] = _column_metrics(result.geometry, T_gt, depth_gt)
    return ClipEval(indices=np.arange(clip.n) if indices is None else np.asarray(indices), stamps=clip.stamps,
                    status=init.status.value, reason=init.reason, mode=outcome.mode, T_gt=T_gt, down_c1=down_c1,
                    init=init, result=result, fast=outcome.fast, columns=columns,
                    init_metrics=metrics.init_metrics(init, clip.gt), decision=outcome.decision,
                    calibration=outcome.calibration,
                    exact_scale=stream.backbone.exact_scale if result is not None else None,
                    backbone_diagnostics=dict(stream.backbone.diagnostics()) if result is not None else {})


def evaluate_frames(seq: Sequence, idx: np.ndarray, backbone: Backbone, *, options: EvalOptions) -> ClipEval:
    """``evaluate_clip`` on the clip of ``seq``'s frames ``idx`` [n], on its own (one clip of
    ``evaluate_sequence``)."""
    return evaluate_clip(make_clip(seq, idx, with_images=backbone.needs_images),
                         options.stream(backbone, online=False), indices=idx)


def clip_label(sequence: str, idx: np.ndarray) -> str:
    """How reports name the clip of frames ``idx`` of ``sequence``."""
    return f"sequence {sequence!r}, clip of frames {int(idx[0])}-{int(idx[-1])}"


def clip_indices(n_frames: int, *, options: EvalOptions, chained: bool = False) -> list[np.ndarray]:
    """Frame indices of the clips to evaluate (``sample_clips``), thinned evenly to ``max_clips``. Chained sliding
    clips without a ``hop`` start every (clip_length - shared_frames) * stride frames, as the node's do: each shares
    its first frames with the clip before it."""
    hop = options.hop
    if hop is None and chained:
        hop = (options.online_options or OnlineOptions()).clip_hop(options.clip_length, options.stride)
    clips = sample_clips(n_frames, n=options.clip_length, stride=options.stride, mode=options.clips, hop=hop)
    if options.max_clips is not None and len(clips) > options.max_clips:
        keep = np.unique(np.linspace(0, len(clips) - 1, options.max_clips).round().astype(int))
        clips = [clips[i] for i in keep]
    return clips


class EvaluationStopped(Vi3Error):
    """An evaluation that failed part-way: ``evals`` (and ``online``, in chained runs) hold what was computed for
    the clips before the one that failed."""

    def __init__(self, message: str, evals: list[ClipEval], online: OnlineRun | None = None) -> None:
        super().__init__(message)
        self.evals, self.online = evals, online


class EvaluationInterrupted(KeyboardInterrupt):
    """An evaluation stopped by Ctrl-C (or a signal raised as KeyboardInterrupt) part-way: ``evals`` (and ``online``)
    as ``EvaluationStopped``."""

    def __init__(self, evals: list[ClipEval], online: OnlineRun | None = None) -> None:
        super().__init__(f"interrupted after {len(evals)} clips")
        self.evals, self.online = evals, online


def interrupted_note(done: int, total: int) -> str:
    """The error of a sequence whose evaluation was interrupted (serial and Ray runs alike)."""
    return f"interrupted: {done} of {total} clips evaluated"


#: Why a sampled clip is not evaluated: the node's clip buffer's reason for the same clip.
IMU_MISSING = "imu_missing"


def check_sequence(seq: Sequence, *, options: EvalOptions, chained: bool = False) -> list[np.ndarray]:
    """The clips ``evaluate_sequence`` (``evaluate_online``: ``chained``) evaluate: those sampled whose frames the IMU
    covers (the others, ``imu_missing``, are skipped as the node skips them); raises DataError when ``seq`` cannot be
    evaluated (no ground truth, no calibration, too short, no clip the IMU covers), before any clip is."""
    if seq.gt is None:
        raise DataError(f"sequence {seq.name!r} has no ground truth; evaluation needs GT poses and velocities")
    if seq.calib is None:
        raise DataError(f"sequence {seq.name!r} has no camera calibration (pass --calib for bags without one)")
    sampled = clip_indices(len(seq.stamps), options=options, chained=chained)
    covered = [idx for idx in sampled if _imu_covers(seq, idx)]
    if not covered:
        span = f"[{seq.imu.t[0]:.6f}, {seq.imu.t[-1]:.6f}] s" if len(seq.imu) else "(no sample)"
        raise DataError(f"sequence {seq.name!r}: the IMU {span} covers none of its {len(sampled)} clips "
                        f"({IMU_MISSING})")
    return covered


def skipped_clips(seq: Sequence, *, options: EvalOptions, chained: bool = False) -> list[np.ndarray]:
    """The sampled clips ``check_sequence`` leaves out (``IMU_MISSING``: no IMU sample at or before the first frame, or
    at or after the last)."""
    return [idx for idx in clip_indices(len(seq.stamps), options=options, chained=chained) if not _imu_covers(seq, idx)]


def _imu_covers(seq: Sequence, idx: np.ndarray) -> bool:
    """Whether ``seq``'s IMU covers the clip of frames ``idx`` (``ImuSamples.covers``)."""
    return seq.imu.covers(seq.stamps[idx[0]], seq.stamps[idx[-1]])


def _stopped(seq: Sequence, idx: np.ndarray, err: Exception, evals: list[ClipEval],
             online: OnlineRun | None = None) -> EvaluationStopped:
    return EvaluationStopped(f"{clip_label(seq.name, idx)}: {err} (the {len(evals)} clips before it were evaluated)",
                             evals, online)


def evaluate_sequence(seq: Sequence, backbone: Backbone, *, options: EvalOptions | None = None) -> list[ClipEval]:
    """Evaluate every sampled clip of ``seq`` (which must have ground truth), with a progress bar over clips.
    A clip that fails raises ``EvaluationStopped`` with the clips evaluated before it, an interruption
    ``EvaluationInterrupted``."""
    options = options or EvalOptions()
    out = []
    try:
        for idx in tqdm(check_sequence(seq, options=options), desc=f"eval {seq.name}", unit="clip",
                        disable=not options.progress):
            try:
                out.append(evaluate_frames(seq, idx, backbone, options=options))
            except (Vi3Error, ValueError, OSError) as err:
                raise _stopped(seq, idx, err, out) from err
    except KeyboardInterrupt:
        raise EvaluationInterrupted(out) from None
    return out


def ablate(seq: Sequence, backbone: Backbone, *, options: EvalOptions | None = None) -> dict[str, list[ClipEval]]:
    """The supplementary initialisation ablations (``ABLATIONS``): one ``evaluate_sequence`` per variant, in
    ``init`` mode with the GT-free initialisation (the variants are its options), each variant's ``InitOptions``
    derived from ``options.init_options`` (or the defaults)."""
    return {name: evaluate_sequence(seq, backbone, options=variant)
            for name, variant in ablation_options(options or EvalOptions()).items()}


def ablation_options(options: EvalOptions) -> dict[str, EvalOptions]:
    """The options of each ``ABLATIONS`` variant: ``options`` in ``init`` mode with the GT-free initialisation and
    the variant's ``InitOptions``, derived from ``options.init_options`` (or the defaults)."""
    base = options.init_options or InitOptions()
    stream = dataclasses.replace(options.stream_options, mode="init", init_source="vi3")
    return {name: dataclasses.replace(options, stream_options=stream,
                                      init_options=dataclasses.replace(base, **overrides))
            for name, overrides in ABLATIONS.items()}


@dataclass
class OnlineRun:
    """The chained run of a sequence: stamps [N] s, T_OB [N,4,4] the odom trajectory, T_WB [N,4,4] GT body poses at
    the same stamps; segment_starts: stamps at which the estimator began a new segment (``Trajectory.resets``);
    decisions: the estimator's description of each clip; resets: clips after the first whose decision restarted the
    state (every reset the decision log records); scale_err [n_clips]: each chained clip's scale error
    (``claims.scale_error``; NaN: no value); independent_status, independent_scale_err, independent_rel_sigma [n_clips]:
    each clip's own GT-free initialisation (what the paper's per-clip pipeline would output) and its relative scale
    sigma; metrics: None when the trajectory cannot be scored, ``reason`` then says why; coverage: how soon and how
    often the run claimed in flight, and its scale links (``vi3_core.eval.coverage``); calibration: the rig's estimate
    after each clip (None without self-calibration) and clip_t0 the first stamp of each clip, s; links: the scale
    links the window used, against the ground truth's ratios (``vi3_core.eval.links``)."""

    stamps: np.ndarray
    T_OB: np.ndarray
    T_WB: np.ndarray
    segment_starts: list[float] = field(default_factory=list)
    decisions: list[str] = field(default_factory=list)
    resets: int = 0
    scale_err: np.ndarray = field(default_factory=lambda: np.zeros(0))
    independent_status: list[str] = field(default_factory=list)
    independent_scale_err: np.ndarray = field(default_factory=lambda: np.zeros(0))
    independent_rel_sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))
    metrics: ChainedMetrics | None = None
    reason: str = ""
    coverage: Coverage | None = None
    calibration: list[RigEstimate | None] = field(default_factory=list)
    clip_t0: list[float] = field(default_factory=list)
    links: list[ScoredLink] = field(default_factory=list)


def contiguity_gap(seq: Sequence, clips: list[np.ndarray], max_gap_s: float) -> str:
    """Why ``clips`` (time-ordered frame indices) cannot be chained: the first stretch between consecutive clips
    longer than ``max_gap_s`` ("" when there is none)."""
    for k in range(1, len(clips)):
        gap = float(seq.stamps[clips[k][0]] - seq.stamps[clips[k - 1][-1]])
        if gap > max_gap_s:
            return (f"not applicable: the clips are not contiguous (frames {clips[k - 1][0]}-{clips[k - 1][-1]} and "
                    f"{clips[k][0]}-{clips[k][-1]} are {gap:.2f} s apart, more than the {max_gap_s:g} s the IMU "
                    "bridges); chain contiguous clips (sliding, not thinned)")
    return ""


def evaluate_online(seq: Sequence, backbone: Backbone, *, options: EvalOptions | None = None,
                    clips: list[np.ndarray] | None = None,
                    on_clip: Callable[[int], None] | None = None) -> tuple[list[ClipEval], OnlineRun]:
    """``evaluate_sequence`` with the metric state carried across clips (``StreamEstimator`` with ``online``, GT-free,
    as the node runs): each clip's initialisation from the stream's window, and the clips chained into one odom
    trajectory, scored against GT per segment. Clips that are not contiguous are still evaluated one by one, but their
    trajectory is not scored (``OnlineRun.reason``). ``clips`` overrides the sampled frame indices (a test leaves a gap
    in the images); ``on_clip(k)`` is called after the k-th clip is evaluated (progress beside the bar). A clip that
    fails raises ``EvaluationStopped`` with what was computed before it, an interruption ``EvaluationInterrupted``."""
    options = options or EvalOptions()
    if options.stream_options.init_source != "vi3":
        raise ValueError("chained evaluation is GT-free: use init_source 'vi3' (or the independent evaluation)")
    sampled = check_sequence(seq, options=options, chained=True)
    clips = sampled if clips is None else clips
    stream = options.stream(backbone, online=True)
    max_bridge = stream.online_options.online_max_bridge
    evals: list[ClipEval] = []
    run = OnlineRun(np.zeros(0), np.zeros((0, 4, 4)), np.zeros((0, 4, 4)))
    try:
        for idx in tqdm(clips, desc=f"eval {seq.name} (chained)", unit="clip", disable=not options.progress):
            try:
                # IMU before the clip over the longest gap the window bridges, as the node's clip buffer keeps it.
                clip = make_clip(seq, idx, history_s=max_bridge, lead_s=stream.imu_lead,
                                 with_images=backbone.needs_images)
                ev = evaluate_clip(clip, stream, indices=idx)
                if len(ev.stamps) != len(idx) or not np.array_equal(ev.stamps, seq.stamps[idx]):
                    ev.indices = np.searchsorted(seq.stamps, ev.stamps)
            except (Vi3Error, ValueError, OSError) as err:
                raise _stopped(seq, idx, err, evals, _finish(seq, stream, run, evals, clips)) from err
            run.decisions.append(ev.decision.describe())
            run.calibration.append(ev.calibration)
            run.clip_t0.append(float(ev.stamps[0]))
            run.resets += bool(evals and ev.decision.reset)  # the first clip of the stream always starts the window
            evals.append(ev)
            if on_clip is not None:
                on_clip(len(evals))
    except KeyboardInterrupt:  # the clips recorded whole (a signal between the appends above drops that clip)
        del run.decisions[len(evals):], run.calibration[len(evals):], run.clip_t0[len(evals):]
        raise EvaluationInterrupted(evals, _finish(seq, stream, run, evals, clips)) from None
    return evals, _finish(seq, stream, run, evals, clips)


def _finish(seq: Sequence, stream: StreamEstimator, run: OnlineRun, evals: list[ClipEval],
            clips: list[np.ndarray]) -> OnlineRun:
    """``run`` completed with the trajectory, the per-clip scale errors of ``evals`` and the metrics."""
    traj = stream.trajectory
    run.stamps, run.T_OB, run.segment_starts = traj.stamps, traj.T_OB, list(traj.resets)
    run.T_WB = seq.gt.at(traj.stamps).T_WB if len(traj.stamps) else np.zeros((0, 4, 4))
    run.scale_err = np.array([scale_error(e, e.mode) for e in evals])
    # Scale (fit) is linear in the scale: the clip's own init's is the base's times its scale (the base's is
    # 1 / exact_scale where the backbone knew that, as claims.scale_error scores it).
    base = np.array([e.base_lam for e in evals])
    own = [e.decision.own for e in evals]
    scale = np.array([o.scale for o in own], dtype=np.float64)
    ok = np.array([o.ok for o in own], dtype=bool)
    run.independent_status = [o.status.value for o in own]
    run.independent_scale_err = np.where(ok, np.abs(base * scale - 1.0), np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        run.independent_rel_sigma = np.array([o.scale_sigma for o in own], dtype=np.float64) / scale
    t0 = np.array([e.stamps[0] for e in evals])
    start = motion_start(seq.gt.t, seq.gt.v_WB, float(t0[0])) if evals else float("nan")
    run.coverage = coverage(t0, [e.stamps[-1] for e in evals], [e.ok for e in evals],
                            [_link_state(e.decision) for e in evals], start)
    run.links = scored_links([e.stamps[0] for e in evals], [_link_of(e.decision) for e in evals], base)
    run.reason = contiguity_gap(seq, clips, stream.online_options.online_max_bridge)
    if not run.reason and len(traj.stamps) < 2:
        run.reason = (f"no trajectory: {len(traj.stamps)} chained poses ({sum(e.ok for e in evals)} of "
                      f"{len(evals)} clips ok)")
    run.metrics = None if run.reason else chained_metrics(run.T_OB, run.T_WB, stamps=run.stamps,
                                                          segment_starts=run.segment_starts,
                                                          path_length=functools.partial(gt_path_length, seq.gt))
    return run


def _link_of(decision: OnlineDecision) -> tuple[float, float, float] | None:
    """(log ratio, sigma, clip_start) of the scale link the window fit used for the clip (None: none)."""
    if decision.link is None:
        return None
    return decision.link.link.log_ratio, decision.link.link.sigma, decision.link.clip_start


def _link_state(decision: OnlineDecision) -> str:
    """"linked", "rejected" or "none" for a clip that joined the window; "" for one that did not."""
    if not decision.joined:
        return ""
    return "linked" if decision.link is not None else "rejected" if decision.link_note.startswith("rejected") \
        else "none"
