"""Aggregate per-clip evaluations into the JSON report and paper-like text tables.

Aggregation follows the paper: every number is the median over clips (NaN values, e.g. Scale (Traj.) of a
stationary clip or depth metrics without GT depth, are left out of the median; a metric with no value is null).
The columns (Base, IMU-init, IMU-cond, TTR) are **paired**: each metric's medians are taken over the same clips,
those whose initialisation was ok (a clip with a rejected or unobservable init has no metric output; it is counted
in ``status_counts``) and whose value of that metric is defined in every column. The base model over all clips is
reported separately (``base_all``). Beside the medians: the claimed clips more than 10 % off and the calibration of
the scale sigmas (``vi3_core.eval.claims``).
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections import Counter
from collections.abc import Iterable, Sequence

import numpy as np

from vi3_core.backbones import front_end
from vi3_core.eval import coverage
from vi3_core.eval.chained import ChainedMetrics, median_after_skip, scored_tail
from vi3_core.eval.claims import (
    Claims,
    clip_claims,
    format_calibration,
    format_outliers,
    rel_sigma,
    trajectory_vs_depth,
)
from vi3_core.eval.clip_eval import ClipEval
from vi3_core.eval.links import LinkScore
from vi3_core.init.initializer import GYRO_FAILURE
from vi3_core.types import InitStatus

METRIC_LABELS: dict[str, str] = {
    "trans_rmse_m": "Trans (m) ↓", "rot_deg": "Rot (deg) ↓", "scale_traj": "Scale (Traj.) →1",
    "scale_fit": "Scale (fit) →1",
    "absrel": "AbsRel ↓", "delta125": "δ<1.25 ↑", "scale_depth": "Scale (Depth) →1",
}
INIT_LABELS: dict[str, str] = {
    "gravity_err_deg": "Gravity (deg) ↓", "gyro_bias_err": "Gyro-bias (rad/s) ↓", "gyro_bias_rel": "Gyro-bias (rel) ↓",
    "v1_dir_deg": "v1 dir. (deg) ↓", "v1_mag_err": "v1 mag. ↓", "v1_mag_ratio": "|v1^|/|v1| →1",
}
COLUMN_LABELS: dict[str, str] = {"base": "Base", "init": "IMU-init", "cond": "IMU-cond", "ttr": "TTR"}
TRAJECTORY_KEYS = tuple(f.name for f in dataclasses.fields(ChainedMetrics) if f.name != "segments")


def _finite(values: Iterable[float | None]) -> np.ndarray:
    arr = np.asarray([v for v in values if v is not None], dtype=np.float64)
    return arr[np.isfinite(arr)]


def _median(values: Iterable[float | None]) -> float | None:
    arr = _finite(values)
    return float(np.median(arr)) if arr.size else None


def _column(evals: Sequence[ClipEval], column: str) -> dict[str, float | None]:
    rows = [e.columns[column].as_dict() for e in evals if column in e.columns]
    return {key: _median(r[key] for r in rows) for key in METRIC_LABELS}


def paired_columns(evals: Sequence[ClipEval], columns: Sequence[str]) -> dict[str, dict[str, float | None]]:
    """Medians of every metric of ``columns`` over the same clips: those that have every column, and of them,
    per metric, those whose value is finite in every column."""
    rows = [e for e in evals if all(c in e.columns for c in columns)]
    out: dict[str, dict[str, float | None]] = {c: {} for c in columns}
    for key in METRIC_LABELS:
        values = np.array([[getattr(e.columns[c], key) for c in columns] for e in rows],
                          dtype=np.float64).reshape(len(rows), len(columns))
        keep = np.isfinite(values).all(axis=1)
        for j, c in enumerate(columns):
            out[c][key] = float(np.median(values[keep, j])) if keep.any() else None
    return out


def expected_columns(mode: str) -> list[str]:
    """The columns an ok clip has in ``mode``: base, the (fast) init, and the refined mode."""
    return ["base", "init"] + ([mode] if mode != "init" else [])


def gyro_check_hint(failed: int, total: int) -> str:
    """The run's hint when most of its ``total`` clips with a result (more than half, and at least 2) were
    ``failed`` by the gyro check: then the input, not the backbone, is the likelier cause; "" otherwise."""
    if failed < 2 or 2 * failed <= total:
        return ""
    return (f"most clips failed the gyro check ({failed} of {total}): a camera-IMU time offset (parameter "
            "time_offset, Kalibr timeshift_cam_imu) or a wrong T_BS (camera pose in the IMU frame) is the likelier "
            "cause than the backbone")


def status_note(evals: Sequence[ClipEval]) -> str:
    """Why no clip claimed a scale ("" when one did): the status counts and the most frequent reason."""
    if any(e.ok for e in evals) or not evals:
        return "" if evals else "no clip evaluated"
    counts = Counter(e.status for e in evals)
    reason, n = Counter(e.reason for e in evals).most_common(1)[0]
    return (f"no clip ok of {len(evals)} ({', '.join(f'{k} {v}' for k, v in counts.items())}); most frequent "
            f"reason ({n}): {reason}")


def _front_end_line(losses: dict | None) -> str:
    if not losses:
        return ""
    lost = ", ".join(f"{100 * v:.1f} % {k.replace('_', ' ')}" for k, v in losses["lost"].items())
    lengths = "" if losses["track_length"] is None else (
        f"; the tracks that ended were seen in {losses['track_length']:.1f} frames on average, "
        f"{100 * losses['long_tracks']:.1f} % of them in {front_end.LONG_TRACK} or more")
    return (f"front end ({losses['frames']} frames, {losses['starts']} started afresh): "
            f"{losses['followed_per_frame']:.0f} tracks followed per frame, lost into the next by the checks: {lost}; "
            f"{losses['new_per_frame']:.0f} new corners per frame, {100 * losses['new_lost']:.0f} % of them lost at "
            f"their first step{lengths}")


def summarise(evals: Sequence[ClipEval], *, mode: str, init_source: str = "vi3", backbone: str = "",
              sequence: str = "") -> dict:
    """The JSON report: ``n_clips``, ``n_ok``, ``n_paired`` (clips in the paired medians), ``columns`` (paired
    medians of every column: base, init, cond/ttr), ``base`` and ``vi3`` (its base and ``mode`` columns),
    ``base_all`` (the base over every clip), ``init`` (median init errors over ok clips), ``claimed_outliers`` and
    ``sigma_calibration`` (``vi3_core.eval.claims``), where the input has depth ground truth the same scored by depth
    (``depth_claims``: ``outliers`` and ``calibration``) and ``trajectory_vs_depth`` (else both None),
    ``status_counts``, ``note`` (why no clip is ok, "" otherwise), ``hint`` (``gyro_check_hint``), ``front_end``
    (``front_end.run_summary``) and a per-clip list."""
    ok = [e for e in evals if e.ok]
    columns = expected_columns(mode)
    paired = [e for e in evals if all(c in e.columns for c in columns)]
    medians = paired_columns(paired, columns)
    init_rows = [e.init_metrics.as_dict() for e in ok if e.init_metrics is not None]
    counts = Counter(e.status for e in evals)
    has_depth = any(np.isfinite(c.scale_depth) for e in evals for c in e.columns.values())
    depth_claims = {"outliers": clip_claims(evals, mode, by_depth=True).outliers(),
                    "calibration": clip_claims(evals, "init", by_depth=True).calibration()} if has_depth else None
    return _plain({
        "sequence": sequence, "backbone": backbone, "mode": mode, "init_source": init_source,
        "n_clips": len(evals), "n_ok": len(ok), "n_paired": len(paired),
        "init": {key: _median(r[key] for r in init_rows) for key in INIT_LABELS},
        "base": medians["base"],
        "vi3": medians[mode],
        "columns": medians,
        "base_all": _column(evals, "base"),
        "claimed_outliers": clip_claims(evals, mode).outliers(),
        "sigma_calibration": clip_claims(evals, "init").calibration(),
        "depth_claims": depth_claims,
        "trajectory_vs_depth": trajectory_vs_depth(evals),
        "status_counts": {s.value: counts.get(s.value, 0) for s in InitStatus},
        "note": status_note(evals),
        "hint": gyro_check_hint(sum(e.reason.startswith(GYRO_FAILURE) for e in evals), len(evals)),
        "front_end": front_end.run_summary(e.backbone_diagnostics.get("front_end") for e in evals),
        "clips": [{"frames": [int(e.indices[0]), int(e.indices[-1])], "t0": float(e.stamps[0]), "status": e.status,
                   "reason": e.reason, "mode": e.mode,
                   "scale_traj": e.columns[mode].scale_traj if mode in e.columns else None,
                   "scale_fit": e.columns[mode].scale_fit if mode in e.columns else None,
                   "scale_depth": e.columns[mode].scale_depth if mode in e.columns else None,
                   "scale_rel_sigma": rel_sigma(e),
                   "traj_depth_sigma": e.traj_depth_sigma,
                   "scale_exact": e.init.scale / e.exact_scale if e.ok and e.exact_scale else None,
                   **({"front_end": e.backbone_diagnostics["front_end"]}
                      if e.backbone_diagnostics.get("front_end") else {}),
                   **({"rig": e.calibration.as_dict()} if e.calibration is not None else {})} for e in evals],
    })


def _plain(value):
    """``value`` with numpy scalars and arrays made Python numbers and lists, and non-finite floats None."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


def to_json(obj) -> str:
    """One strictly valid JSON document: NaN and +-Inf become null, numpy values plain numbers and lists."""
    return json.dumps(_plain(obj), allow_nan=False)


def _fmt(value: float | None, key: str) -> str:
    if value is None:
        return "--"
    if key.endswith("err_median") or key.endswith("sigma"):
        return f"{value:.4f}"
    if key == "scale_fit":  # the trust metrics' reference: per-cent errors need the third decimal
        return f"{value:.3f}"
    return f"{value:.2f}" if key.startswith("scale") or key.endswith("ratio") else f"{value:.3f}"


def _grid(header: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    line = "  ".join("-" * w for w in widths)
    fmt = [h.ljust(widths[0]) if i == 0 else h.rjust(widths[i]) for i, h in enumerate(header)]
    body = ["  ".join(c.ljust(widths[0]) if i == 0 else c.rjust(widths[i]) for i, c in enumerate(r)) for r in rows]
    return "\n".join(["  ".join(fmt), line, *body])


def format_tables(summary: dict) -> str:
    """Paper-like text tables: metrics x (Base / IMU-init / IMU-cond / TTR, paired; Base over all clips), the claimed
    outliers and sigma calibration, then the init errors."""
    cols = list(summary["columns"])
    n = summary["n_clips"]
    title = (f"VI3 evaluation: {summary['sequence'] or 'sequence'} | backbone {summary['backbone'] or '?'} | "
             f"mode {summary['mode']} | init {'GT-free' if summary['init_source'] == 'vi3' else 'GT (oracle)'} | "
             f"{n} clip{'' if n == 1 else 's'}, {summary['n_ok']} ok; medians over the {summary['n_paired']} paired "
             f"clips (ok), Base (all) over all {n}")
    rows = [[label, *(_fmt(summary["columns"][c][key], key) for c in cols), _fmt(summary["base_all"][key], key)]
            for key, label in METRIC_LABELS.items()]
    init_rows = [[label, _fmt(summary["init"][key], key)] for key, label in INIT_LABELS.items()]
    status = ", ".join(f"{k} {v}" for k, v in summary["status_counts"].items())
    claims = (f"claimed scales (ok clips) more than 10 % off: {format_outliers(summary['claimed_outliers'])}; "
              f"scale sigma: {format_calibration(summary['sigma_calibration'])}")
    parts = [title, _grid(["Metric", *(COLUMN_LABELS[c] for c in cols), "Base (all)"], rows), claims,
             _depth_line(summary.get("depth_claims"), summary.get("trajectory_vs_depth")),
             _grid(["Initialisation", "error"], init_rows), f"clip status: {status}",
             _front_end_line(summary.get("front_end"))]
    if summary.get("depth_gt", "").startswith("unreadable"):
        parts.append(f"depth ground truth {summary['depth_gt']}")
    return "\n\n".join([p for p in parts if p] + [summary[k] for k in ("note", "hint") if summary.get(k)])


def _depth_line(claims: dict | None, apart: dict | None) -> str:
    """The claims scored by their depth and the predictions' trajectory against their depth ("" without depth ground
    truth)."""
    if claims is None:
        return ""
    line = (f"by depth: claimed scales more than 10 % off: {format_outliers(claims['outliers'])}; "
            f"scale sigma: {format_calibration(claims['calibration'])}")
    if apart is not None:
        line += (f"; the backbone's trajectory against its depth: median scale ratio {apart['median']:.3f}, "
                 f"{apart['apart']} of {apart['clips']} clips more than 10 % apart")
        if apart.get("sigmas") is not None:
            line += f", spread {apart['sigmas']:.2f} times its traj_depth_sigma"
    return line


def format_clips(summary: dict) -> str:
    """The per-clip table: frames, start (s after the first clip), status, Scale (Traj.) of the VI3 column and the
    relative scale sigma; in chained runs also each clip's own GT-free initialisation and the estimator's decision;
    then the reason."""
    clips = summary["clips"]
    if not clips:
        return "no clips"
    chained = summary.get("chained")
    header = ["#", "frames", "t (s)", "status", "Scale (Traj.)", "Scale (fit)", "rel. sigma"]
    if chained:
        header += ["own init", "own |err|", "own sigma"]
    rows = []
    for k, c in enumerate(clips):
        row = [str(k), f"{c['frames'][0]}-{c['frames'][1]}", f"{c['t0'] - clips[0]['t0']:.2f}", c["status"],
               _fmt(c["scale_traj"], "scale_traj"), _fmt(c["scale_fit"], "scale_fit"),
               _fmt(c["scale_rel_sigma"], "rel_sigma")]
        if chained:
            own = chained["independent_clips"][k]
            row += [own["status"], _fmt(own["scale_err"], "err_median"), _fmt(own["scale_rel_sigma"], "rel_sigma")]
        rows.append(row)
    table = _grid(header, rows).splitlines()
    notes = [f"  {c['reason']}" + (f" | {chained['decisions'][k]}" if chained else "") for k, c in enumerate(clips)]
    body = [line for pair in zip(table[2:], notes) for line in pair]
    skipped = [f"skipped: frames {c['frames'][0]}-{c['frames'][1]} ({c['reason']})"
               for c in summary.get("skipped_clips", [])]
    return "\n".join([f"Per clip: {summary['sequence']} (reason | online decision)", *table[:2], *body, *skipped])


def format_ablation(summaries: dict[str, dict]) -> str:
    """The supplementary init ablations: one row per variant (its ``vi3`` column and init errors)."""
    geo = ("trans_rmse_m", "scale_traj", "scale_depth")
    ini = ("gravity_err_deg", "v1_dir_deg", "v1_mag_ratio")
    header = ["Variant", *(METRIC_LABELS[k] for k in geo), *(INIT_LABELS[k] for k in ini), "ok/clips"]
    rows = [[name, *(_fmt(s["vi3"][k], k) for k in geo), *(_fmt(s["init"][k], k) for k in ini),
             f"{s['n_ok']}/{s['n_clips']}"] for name, s in summaries.items()]
    return "Initialisation ablations (supplementary tables), median over clips\n\n" + _grid(header, rows)


def independent_claims(run) -> Claims:
    """The claims of the chained clips' own GT-free initialisation (``runner.OnlineRun``)."""
    return Claims.of(run.independent_scale_err, run.independent_rel_sigma)


def chained_summary(run) -> dict:
    """The ``chained`` JSON object of a ``runner.OnlineRun``: ``applicable`` and ``reason`` (why the trajectory is
    not scored), the ``ChainedMetrics`` (``ate_m``, ``drift_pct``, ``gravity_err_deg``, ``distance_m``, ``frames``,
    ``segments`` count, ``per_segment``; None when not scored), ``resets``, the per-clip scale error medians
    (``scale_err_median`` chained, ``independent_scale_err_median`` the clips' own GT-free initialisation), that
    initialisation's ``independent_claimed_outliers`` and ``independent_sigma_calibration``, and per clip the
    ``decisions`` (window, priors used, rejected with reasons, resets) and ``independent_clips``."""
    m = run.metrics.as_dict() if run.metrics is not None else {**dict.fromkeys(TRAJECTORY_KEYS), "segments": None,
                                                                  "per_segment": []}
    own = independent_claims(run)
    return _plain({
        "applicable": run.metrics is not None, "reason": run.reason, **m, "resets": run.resets,
        **(run.coverage.as_dict() if run.coverage is not None else {}),
        "calibration": calibration_summary(run),
        "link_errors": LinkScore.of([run.links]).as_dict(),
        "scale_err_median": median_after_skip(run.scale_err),
        "independent_scale_err_median": median_after_skip(run.independent_scale_err),
        "independent_claimed_outliers": own.outliers(), "independent_sigma_calibration": own.calibration(),
        "decisions": list(run.decisions),
        "independent_clips": [{"status": st, "scale_err": err, "scale_rel_sigma": sg} for st, err, sg in
                              zip(run.independent_status, run.independent_scale_err, run.independent_rel_sigma)],
    })


def calibration_summary(run) -> dict | None:
    """The rig's self-calibration in a chained run (``runner.OnlineRun``): the final estimate relative to the
    configuration (mount rotation about the body axes, deg, and time offset, ms, each with its 1-sigma and whether it
    replaced the configuration) and when each first did (s after the first clip); None without self-calibration."""
    known = [(t, c) for t, c in zip(run.clip_t0, run.calibration) if c is not None]
    if not known:
        return None
    final, t0 = known[-1][1], known[0][0]

    def first(flag: str) -> float | None:
        return next((float(t - t0) for t, c in known if getattr(c, flag)), None)

    return {**final.as_dict(), "rotation_applied_after_s": first("rotation_applied"),
            "offset_applied_after_s": first("offset_applied")}


def pool_chained(named_runs: Sequence[tuple[str, object]]) -> dict:
    """The chained results of several sequences, ``(name, runner.OnlineRun)`` pairs: the per-clip scale errors
    pooled (``scale_err_median``, ``independent_scale_err_median``: medians over every sequence's
    ``chained.scored_tail``), the pooled ``independent_claimed_outliers`` / ``independent_sigma_calibration``, the
    worst ``ate_m``, ``drift_pct`` and ``gravity_err_deg`` over the ``scored`` sequences, the total ``segments``
    and ``resets``, and ``not_scored``: every sequence whose trajectory was not scored, with the reason."""
    scored = [r for _, r in named_runs if r.metrics is not None]
    own = Claims.concatenate(independent_claims(r) for _, r in named_runs)
    return _plain({
        "sequences": len(named_runs), "scored": len(scored),
        "not_scored": [{"sequence": name, "reason": r.reason} for name, r in named_runs if r.metrics is None],
        "scale_err_median": _median(np.concatenate([[], *(scored_tail(r.scale_err) for _, r in named_runs)])),
        "independent_scale_err_median": _median(np.concatenate(
            [[], *(scored_tail(r.independent_scale_err) for _, r in named_runs)])),
        "independent_claimed_outliers": own.outliers(), "independent_sigma_calibration": own.calibration(),
        **{f"{key}_max": _finite_max(getattr(r.metrics, key) for r in scored)
           for key in ("ate_m", "drift_pct", "gravity_err_deg")},
        "segments": sum(len(r.metrics.segments) for r in scored),
        "resets": sum(r.resets for _, r in named_runs),
        **coverage.pool(r.coverage for _, r in named_runs if r.coverage is not None),
        "link_errors": LinkScore.of(r.links for _, r in named_runs).as_dict(),
    })


def _finite_max(values: Iterable[float | None]) -> float | None:
    arr = _finite(values)
    return float(arr.max()) if arr.size else None


def _claims_line(prefix: str, outliers: dict, calibration: dict) -> str:
    return (f"{prefix} claimed scales more than 10 % off: {format_outliers(outliers)}; scale sigma: "
            f"{format_calibration(calibration)}")


def _coverage_line(chained: dict) -> str:
    """How soon and how often a chained run (or a pool of them) claimed in flight, and its scale links."""
    flight, links = chained.get("in_flight"), chained.get("links")
    if flight is None:
        return ""
    first = chained.get("first_claim_after_motion_s", chained.get("first_claim_after_motion_s_max"))
    share = f"{100 * flight['share']:.0f} %" if flight["share"] is not None else "--"
    return (f"in flight (from {coverage.IN_FLIGHT_AFTER_S:g} s after motion starts): {flight['claimed']} of "
            f"{flight['clips']} clips claimed ({share}); first claim "
            + (f"{first:.1f} s after motion starts" if first is not None else "never")
            + f"; scale links: {links['accepted']} used, {links['rejected']} refused, {links['none']} none")


def _links_line(chained: dict) -> str:
    """The scale links against the ground truth (``LinkScore``), or "" where none was scored."""
    d = chained.get("link_errors")
    if not d or not d["scored"]:
        return ""
    text = (f"scale links against the ground truth: {d['scored']} scored, median |z| {d['z_median']:.2f}, "
            f"{100 * d['within_2sigma']:.0f} % within 2 sigma (median sigma {100 * d['sigma_median']:.2f} %)")
    if d["per_link_sd"] is not None:
        text += (f"; from chains: {100 * d['per_link_sd']:.2f} % per link, the ground truth's own "
                 f"{100 * d['reference_sd']:.2f} % per clip")
    return text


def _calibration_line(calibration: dict | None) -> str:
    if calibration is None:
        return "rig: as configured (self_calibration off)"
    rot = " ".join(f"{a:+.2f}+-{s:.2f}" for a, s in zip(calibration["rotation_deg"], calibration["rotation_sigma_deg"]))

    def when(key: str) -> str:
        t = calibration[f"{key}_applied_after_s"]
        return f"applied after {t:.1f} s" if t is not None else "not applied"

    return (f"rig: mount rotation [{rot}] deg ({when('rotation')}), time offset {calibration['time_offset_ms']:+.2f}+-"
            f"{calibration['time_offset_sigma_ms']:.2f} ms ({when('offset')}), relative to the configuration")


def format_chained(chained: dict, summary: dict) -> str:
    """The chained trajectory's metrics (per segment when there are several), the per-clip scale errors and the
    claims of the chained clips (``summary``: their ``summarise``) beside those of the clips' own initialisation."""
    title = "Chained odom trajectory (yaw + position of each segment's first pose aligned)"
    scales = _one_row(chained, ("scale_err_median", "independent_scale_err_median", "resets"))
    lines = [_claims_line("chained:", summary["claimed_outliers"], summary["sigma_calibration"]),
             _claims_line("own init:", chained["independent_claimed_outliers"],
                          chained["independent_sigma_calibration"]), _coverage_line(chained),
             _links_line(chained), _calibration_line(chained.get("calibration"))]
    claims = "\n".join(line for line in lines if line)
    if not chained["applicable"]:
        return f"{title}: {chained['reason']}\n{scales}\n{claims}"
    traj = _one_row(chained, ("ate_m", "drift_pct", "gravity_err_deg", "distance_m", "frames", "segments"))
    parts = [f"{title}\n{traj}"]
    if chained["segments"] > 1:
        keys = ("t0", "t1", "frames", "distance_m", "ate_m", "drift_pct")
        rows = [[str(k), *(str(s[key]) if key == "frames" else f"{s[key]:.2f}" if key in ("t0", "t1")
                           else _fmt(s[key], key) for key in keys)] for k, s in enumerate(chained["per_segment"])]
        parts.append(_grid(["segment", *keys], rows))
    return "\n".join([*parts, scales, claims])


def format_pooled_chained(pooled: dict) -> str:
    """One table of ``pool_chained``'s metrics, the pooled claims of the clips' own initialisation, and a line per
    sequence whose trajectory was not scored."""
    keys = ("scale_err_median", "independent_scale_err_median", "ate_m_max", "drift_pct_max", "gravity_err_deg_max",
            "segments", "resets")
    lines = [f"Chained odom trajectories, {pooled['sequences']} sequences pooled ({pooled['scored']} scored)",
             _one_row(pooled, keys),
             _claims_line("own init:", pooled["independent_claimed_outliers"],
                          pooled["independent_sigma_calibration"]), _coverage_line(pooled), _links_line(pooled)]
    lines = [line for line in lines if line]
    lines += [f"not scored: {s['sequence']}: {s['reason']}" for s in pooled["not_scored"]]
    return "\n".join(lines)


def format_overview(sequences: Sequence[dict]) -> str:
    """One line per sequence, evaluated or not: clips, ok, paired, VI3 Scale (Traj.), claimed outliers, chained
    ATE and drift (or why there are none), and the error or note."""
    header = ["Sequence", "clips", "ok", "paired", "Scale (Traj.)", "claimed >10 % off", "ATE (m)", "drift (%)",
              "note"]
    rows = []
    for s in sequences:
        if "error" in s and "n_clips" not in s:
            rows.append([s["sequence"], *["--"] * 7, f"error: {s['error']}"])
            continue
        ch = s.get("chained") or {}
        note = s.get("error", "") or s["note"] or (ch.get("reason", "") if ch else "")
        rows.append([s["sequence"], str(s["n_clips"]), str(s["n_ok"]), str(s["n_paired"]),
                     _fmt(s["vi3"]["scale_traj"], "scale_traj"), format_outliers(s["claimed_outliers"]),
                     _fmt(ch.get("ate_m"), "ate_m"), _fmt(ch.get("drift_pct"), "drift_pct"), note])
    return "Sequences\n" + _grid(header, rows)


def _one_row(values: dict, keys: tuple[str, ...]) -> str:
    """A one-row table of ``values[k]`` for ``keys`` (integers as they are)."""
    return _grid(list(keys), [[str(values[k]) if isinstance(values[k], int) else _fmt(values[k], k) for k in keys]])
