"""Aggregate per-clip evaluations into the JSON report and paper-like text tables.

Aggregation follows the paper: every number is the median over clips (NaN values, e.g. Scale (Traj.) of a
stationary clip or depth metrics without GT depth, are left out of the median; a metric with no value is null).
The Base column uses every clip; the VI3 columns use the clips whose initialisation was ok (a clip with a
rejected or unobservable init has no metric output; it is counted in ``status_counts``).
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections import Counter
from collections.abc import Iterable, Sequence

import numpy as np

from vi3_core.eval.chained import ChainedMetrics, count_outliers, scored_tail
from vi3_core.eval.clip_eval import ClipEval
from vi3_core.types import InitStatus

METRIC_LABELS: dict[str, str] = {
    "trans_rmse_m": "Trans (m) ↓", "rot_deg": "Rot (deg) ↓", "scale_traj": "Scale (Traj.) →1",
    "absrel": "AbsRel ↓", "delta125": "δ<1.25 ↑", "scale_depth": "Scale (Depth) →1",
}
INIT_LABELS: dict[str, str] = {
    "gravity_err_deg": "Gravity (deg) ↓", "gyro_bias_err": "Gyro-bias (rad/s) ↓", "gyro_bias_rel": "Gyro-bias (rel) ↓",
    "v1_dir_deg": "v1 dir. (deg) ↓", "v1_mag_err": "v1 mag. ↓", "v1_mag_ratio": "|v1^|/|v1| →1",
}
COLUMN_LABELS: dict[str, str] = {"base": "Base", "init": "IMU-init", "cond": "IMU-cond", "ttr": "TTR"}


def _finite(values: Iterable[float | None]) -> np.ndarray:
    arr = np.asarray([v for v in values if v is not None], dtype=np.float64)
    return arr[np.isfinite(arr)]


def _median(values: Iterable[float | None]) -> float | None:
    arr = _finite(values)
    return float(np.median(arr)) if arr.size else None


def _column(evals: Sequence[ClipEval], column: str) -> dict[str, float | None]:
    rows = [e.columns[column].as_dict() for e in evals if column in e.columns]
    return {key: _median(r[key] for r in rows) for key in METRIC_LABELS}


def summarise(evals: Sequence[ClipEval], *, mode: str, init_source: str = "vi3", backbone: str = "",
              sequence: str = "") -> dict:
    """The JSON report: ``n_clips``, ``init`` (median init errors over ok clips), ``base`` and ``vi3`` (median
    metrics; ``vi3`` is the column of ``mode``), ``columns`` (every column evaluated: base, init, cond/ttr),
    ``status_counts`` (clips per init status) and a per-clip list."""
    ok = [e for e in evals if e.ok]
    columns = [c for c in COLUMN_LABELS if any(c in e.columns for e in evals)]
    init_rows = [e.init_metrics.as_dict() for e in ok if e.init_metrics is not None]
    counts = Counter(e.status for e in evals)
    return {
        "sequence": sequence, "backbone": backbone, "mode": mode, "init_source": init_source,
        "n_clips": len(evals), "n_ok": len(ok),
        "init": {key: _median(r[key] for r in init_rows) for key in INIT_LABELS},
        "base": _column(evals, "base"),
        "vi3": _column(evals, mode),
        "columns": {c: _column(evals, c) for c in columns},
        "status_counts": {s.value: counts.get(s.value, 0) for s in InitStatus},
        "clips": [{"frames": [int(e.indices[0]), int(e.indices[-1])], "t0": float(e.stamps[0]), "status": e.status,
                   "reason": e.reason, "mode": e.mode} for e in evals],
    }


def to_json(summary: dict) -> str:
    """One JSON object (no NaN: missing values are null)."""
    return json.dumps(summary, allow_nan=False)


def _fmt(value: float | None, key: str) -> str:
    if value is None:
        return "--"
    if key.endswith("err_median"):
        return f"{value:.4f}"
    return f"{value:.2f}" if key.startswith("scale") or key.endswith("ratio") else f"{value:.3f}"


def _grid(header: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    line = "  ".join("-" * w for w in widths)
    fmt = [h.ljust(widths[0]) if i == 0 else h.rjust(widths[i]) for i, h in enumerate(header)]
    body = ["  ".join(c.ljust(widths[0]) if i == 0 else c.rjust(widths[i]) for i, c in enumerate(r)) for r in rows]
    return "\n".join(["  ".join(fmt), line, *body])


def format_tables(summary: dict) -> str:
    """Paper-like text tables: metrics x (Base / IMU-init / IMU-cond / TTR), then the init errors."""
    cols = list(summary["columns"])
    title = (f"VI3 evaluation: {summary['sequence'] or 'sequence'} | backbone {summary['backbone'] or '?'} | "
             f"mode {summary['mode']} | init {'GT-free' if summary['init_source'] == 'vi3' else 'GT (oracle)'} | "
             f"{summary['n_clips']} clip{'' if summary['n_clips'] == 1 else 's'}, median over clips")
    rows = [[label, *(_fmt(summary["columns"][c][key], key) for c in cols)] for key, label in METRIC_LABELS.items()]
    init_rows = [[label, _fmt(summary["init"][key], key)] for key, label in INIT_LABELS.items()]
    status = ", ".join(f"{k} {v}" for k, v in summary["status_counts"].items())
    return "\n\n".join([title, _grid(["Metric", *(COLUMN_LABELS[c] for c in cols)], rows),
                        _grid(["Initialisation", "error"], init_rows), f"clip status: {status}"])


def format_ablation(summaries: dict[str, dict]) -> str:
    """The supplementary init ablations: one row per variant (its ``vi3`` column and init errors)."""
    geo = ("trans_rmse_m", "scale_traj", "scale_depth")
    ini = ("gravity_err_deg", "v1_dir_deg", "v1_mag_ratio")
    header = ["Variant", *(METRIC_LABELS[k] for k in geo), *(INIT_LABELS[k] for k in ini), "ok/clips"]
    rows = [[name, *(_fmt(s["vi3"][k], k) for k in geo), *(_fmt(s["init"][k], k) for k in ini),
             f"{s['n_ok']}/{s['n_clips']}"] for name, s in summaries.items()]
    return "Initialisation ablations (supplementary tables), median over clips\n\n" + _grid(header, rows)


def chained_summary(run) -> dict:
    """The ``chained`` JSON object of a ``runner.OnlineRun``: the ``ChainedMetrics`` fields (``ate_m``,
    ``drift_pct``, ``gravity_err_deg``, ``resets``, ``scale_err_median``, ``independent_scale_err_median``, ...;
    None when fewer than 2 poses were chained or without a value) and the per-clip ``decisions`` (window, priors
    used, rejected with reasons, resets)."""
    m = run.metrics.as_dict() if run.metrics is not None else dict.fromkeys(
        f.name for f in dataclasses.fields(ChainedMetrics))
    m = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in m.items()}
    return {**m, "decisions": list(run.decisions)}


def pool_chained(runs: Sequence) -> dict:
    """The chained metrics of several sequences' ``runner.OnlineRun``s: the per-clip scale errors pooled
    (``scale_err_median``, ``independent_scale_err_median``: medians over every sequence's ``chained.scored_tail``),
    the worst ``ate_m``, ``drift_pct`` and ``gravity_err_deg``, the total ``resets`` and the total
    ``scale_outliers`` / ``independent_scale_outliers``."""
    worst = {key: _finite_max(getattr(r.metrics, key) for r in runs if r.metrics is not None)
             for key in ("ate_m", "drift_pct", "gravity_err_deg")}
    return {
        "sequences": len(runs),
        "scale_err_median": _median(np.concatenate([scored_tail(r.scale_err) for r in runs])),
        "independent_scale_err_median": _median(np.concatenate([scored_tail(r.independent_scale_err) for r in runs])),
        **{f"{key}_max": value for key, value in worst.items()},
        "resets": sum(r.metrics.resets for r in runs if r.metrics is not None),
        "scale_outliers": sum(count_outliers(r.scale_err) for r in runs),
        "independent_scale_outliers": sum(count_outliers(r.independent_scale_err) for r in runs),
    }


def _finite_max(values: Iterable[float | None]) -> float | None:
    arr = _finite(values)
    return float(arr.max()) if arr.size else None


def format_chained(chained: dict) -> str:
    """One table of the chained trajectory's metrics."""
    keys = ("ate_m", "drift_pct", "gravity_err_deg", "resets", "distance_m", "scale_err_median",
            "independent_scale_err_median", "scale_outliers", "independent_scale_outliers")
    return "Chained odom trajectory (yaw + position of the first pose aligned)\n" + _one_row(chained, keys)


def format_pooled_chained(pooled: dict) -> str:
    """One table of ``pool_chained``'s metrics."""
    keys = ("scale_err_median", "independent_scale_err_median", "ate_m_max", "drift_pct_max", "gravity_err_deg_max",
            "resets", "scale_outliers", "independent_scale_outliers")
    return f"Chained odom trajectories, {pooled['sequences']} sequences pooled\n" + _one_row(pooled, keys)


def _one_row(values: dict, keys: tuple[str, ...]) -> str:
    """A one-row table of ``values[k]`` for ``keys`` (integers as they are)."""
    return _grid(list(keys), [[str(values[k]) if isinstance(values[k], int) else _fmt(values[k], k) for k in keys]])
