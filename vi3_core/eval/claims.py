"""How far the claimed scales can be trusted: the clips reported ``ok`` whose scale is more than ``SCALE_OUTLIER``
off (a confident wrong scale, the number a user of a metric node cares about most), and how well each clip's own
scale sigma (``InitResult.scale_sigma``) predicts its error.

A clip's error is |Scale (fit) - 1| (the least-squares ratio of its metric to the true camera positions,
``metrics.scale_fit``: it weighs long baselines, so pose noise passes for little scale error where the clip moves;
clips without one, e.g. stationary ones, are not scored) and its relative sigma ``scale_sigma / scale``; a calibrated
sigma has about 68 % / 95 % of the errors within 1 / 2 sigma (Gaussian errors). The ground-truth instrument's clips
are scored against the scale it predicted at, which it knows exactly (``ClipEval.exact_scale``): on a clip that
moves a centimetre its pose noise would otherwise read as a scale error of tens of per cent.

Where the input has depth ground truth, the same claims are also scored by their depth, |Scale (depth) - 1|
(``metrics.scale_depth``), and each clip's prediction by how far its trajectory's scale and its depth's disagree
(``trajectory_vs_depth``): one scale serves both, so a claim right by its depth and wrong by its trajectory is a
backbone whose poses do not fit its own depth, not a wrong scale.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from vi3_core.eval.clip_eval import ClipEval

SCALE_OUTLIER = 0.1
NO_SIGMA = "no sigma: no claimed clip reports a scale sigma"


@dataclass(frozen=True)
class Claims:
    """The clips that claimed a scale (status ok) and have a Scale (fit): errors [n] |Scale (fit) - 1|,
    rel_sigma [n] their relative 1-sigma (NaN where none was reported)."""

    errors: np.ndarray
    rel_sigma: np.ndarray

    @staticmethod
    def of(errors: Iterable[float], rel_sigma: Iterable[float]) -> Claims:
        """From per-clip values [n] (NaN error: the clip claimed no scale, or has no Scale (fit); dropped)."""
        e = np.asarray(list(errors), dtype=np.float64).reshape(-1)
        s = np.asarray(list(rel_sigma), dtype=np.float64).reshape(-1)
        if e.shape != s.shape:
            raise ValueError(f"Claims.of: {e.size} errors for {s.size} sigmas")
        keep = np.isfinite(e)
        return Claims(e[keep], s[keep])

    @staticmethod
    def concatenate(parts: Iterable[Claims]) -> Claims:
        parts = list(parts)
        return Claims(np.concatenate([np.zeros(0), *(p.errors for p in parts)]),
                      np.concatenate([np.zeros(0), *(p.rel_sigma for p in parts)]))

    def outliers(self) -> dict:
        """``count`` of claimed clips more than SCALE_OUTLIER off, of ``claimed``, and their ``share`` (None when
        nothing was claimed)."""
        n, bad = len(self.errors), int((self.errors > SCALE_OUTLIER).sum())
        return {"count": bad, "claimed": n, "share": bad / n if n else None}

    def calibration(self) -> dict:
        """``with_sigma``: claimed clips that report a sigma; ``within_1sigma`` / ``within_2sigma``: the share of
        those whose error is within 1 / 2 relative sigma (None, and ``note`` NO_SIGMA, when none reports one)."""
        has = np.isfinite(self.rel_sigma) & (self.rel_sigma >= 0)
        e, s = self.errors[has], self.rel_sigma[has]
        out = {"claimed": len(self.errors), "with_sigma": int(has.sum()),
               "within_1sigma": float(np.mean(e <= s)) if e.size else None,
               "within_2sigma": float(np.mean(e <= 2.0 * s)) if e.size else None}
        return out if e.size else {**out, "note": NO_SIGMA}


def rel_sigma(e: ClipEval) -> float:
    """The clip's relative scale sigma ``scale_sigma / scale`` (NaN when unknown)."""
    init = e.init
    return float(init.scale_sigma / init.scale) if init.scale > 0 else float("nan")


def scale_error(e: ClipEval, column: str) -> float:
    """|Scale (fit) - 1| of the clip's ``column`` (NaN when it has none); for a claimed clip of a backbone that knew
    its prediction's scale exactly (``ClipEval.exact_scale``), the claimed scale's own error |scale / exact - 1|."""
    if column not in e.columns:
        return float("nan")
    if e.ok and e.exact_scale is not None and column == e.mode:
        return abs(e.init.scale / e.exact_scale - 1.0)
    return abs(e.columns[column].scale_fit - 1.0)


def depth_scale_error(e: ClipEval, column: str) -> float:
    """|Scale (depth) - 1| of the clip's ``column`` (NaN where it has none, or no depth ground truth)."""
    return abs(e.columns[column].scale_depth - 1.0) if column in e.columns else float("nan")


def clip_claims(evals: Sequence[ClipEval], column: str, *, by_depth: bool = False) -> Claims:
    """The claims of the evaluated clips' ``column`` ("init", "cond", "ttr": the VI3 output; "init" is what the
    sigma describes), with the initialisation's relative sigma; ``by_depth``: scored by their depth
    (``depth_scale_error``) instead of their trajectory."""
    ok = [e for e in evals if e.ok]
    error = depth_scale_error if by_depth else scale_error
    return Claims.of((error(e, column) for e in ok), (rel_sigma(e) for e in ok))


def trajectory_vs_depth(evals: Sequence[ClipEval]) -> dict | None:
    """How far each clip's prediction has its trajectory at another scale than its depth: per clip with both, the
    ratio Scale (fit) / Scale (depth) of its base column; ``clips`` scored, their ``median`` ratio and ``apart``, those
    more than SCALE_OUTLIER from 1, and ``sigmas``: the robust 1-sigma (1.4826 MAD) of log(ratio) over the
    backbone's own ``traj_depth_sigma`` of each clip that has one (1 where the backbone's sigma is what it says; None
    where no clip has one) (None without depth ground truth)."""
    rows = np.array([(e.columns["base"].scale_fit / e.columns["base"].scale_depth,
                      e.traj_depth_sigma or 0.0) for e in evals
                     if "base" in e.columns and e.columns["base"].scale_depth > 0]).reshape(-1, 2)
    rows = rows[np.isfinite(rows[:, 0]) & (rows[:, 0] > 0)]
    if not len(rows):
        return None
    ratio, sigma = rows.T
    z = np.log(ratio[sigma > 0]) / sigma[sigma > 0]
    return {"clips": int(ratio.size), "median": float(np.median(ratio)),
            "apart": int((np.abs(ratio - 1.0) > SCALE_OUTLIER).sum()),
            "sigmas": float(1.4826 * np.median(np.abs(z - np.median(z)))) if z.size else None}


def format_outliers(outliers: dict) -> str:
    """'k of n (x %)' for ``Claims.outliers``."""
    if not outliers["claimed"]:
        return "none claimed"
    return f"{outliers['count']} of {outliers['claimed']} ({100.0 * outliers['share']:.1f} %)"


def format_calibration(cal: dict) -> str:
    """One phrase for ``Claims.calibration``."""
    if not cal["with_sigma"]:
        return "no sigma"
    return (f"{100.0 * cal['within_1sigma']:.0f} % within 1 sigma, {100.0 * cal['within_2sigma']:.0f} % within "
            f"2 sigma (of {cal['with_sigma']} of {cal['claimed']} claimed clips with a sigma)")
