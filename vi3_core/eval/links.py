"""The window's scale links against the ground truth: is each link's ratio what the two clips' scales really are, and
is its sigma honest?

A link says lam_k / lam_j (model units per metre of clips k and j, ``vi3_core.online.link``). The ground truth's
ratio is that of the two clips' own scales against it (``ClipEval.base_lam``: each prediction's least-squares scale
on the ground truth's camera positions). That reference is itself noisy: a clip's positions carry its prediction's
noise, so over a short clip its scale is good to a few per cent, and a single link's error then mixes the link's
with the reference's. Chains separate the two: the error of n consecutive links' summed log ratio against the ratio
of the chain's two end clips has the variance n sigma_link^2 + 2 sigma_ref^2 (the links' errors add, the reference
enters at the two ends only); a line through the robust variances at several n gives both.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

CHAIN_LENGTHS = (1, 2, 3, 4, 6, 8)  # links per chain in the fit of the errors' growth
MIN_CHAINS = 8  # chains of one length needed for its variance to enter the fit
SAME_CLIP_S = 1e-3  # s: a link's target clip is the clip that starts within this of the link's clip_start


@dataclass(frozen=True)
class ScoredLink:
    """One link a window fit used: measured log ratio and its 1-sigma, the ground truth's log ratio, and whether it
    links consecutive clips of the run (``run_index``: the later clip's index; chains are runs of these)."""

    log_ratio: float
    sigma: float
    true_log_ratio: float
    consecutive: bool
    run_index: int


def scored_links(stamps0: Sequence[float], links: Sequence[tuple[float, float, float] | None],
                 base_lam: Sequence[float]) -> list[ScoredLink]:
    """The links of a chained run whose two clips have a ground-truth scale: per clip k, its first stamp
    ``stamps0[k]`` (s), the link it joined the window with (``(log_ratio, sigma, clip_start)``, None: none) and
    ``base_lam[k]`` (model units per metre against the ground truth; NaN: none)."""
    t0 = np.asarray(stamps0, float)
    lam = np.asarray(base_lam, float)
    out = []
    for k, link in enumerate(links):
        if link is None:
            continue
        log_ratio, sigma, clip_start = link
        named = np.flatnonzero(np.abs(t0[:k] - clip_start) <= SAME_CLIP_S)  # the latest: clips may share a start
        j = int(named[-1]) if len(named) else -1
        if j < 0 or not (lam[k] > 0 and lam[j] > 0):
            continue
        out.append(ScoredLink(log_ratio, sigma, math.log(lam[k] / lam[j]), j == k - 1, k))
    return out


def _robust_var(x: np.ndarray) -> float:
    """A robust second moment of the errors x [m] about zero (a bias of the links counts: it grows along a chain)."""
    return float((1.4826 * np.median(np.abs(x))) ** 2)


def chain_errors(links: Sequence[ScoredLink], n: int) -> np.ndarray:
    """The errors of every chain of ``n`` consecutive links (summed measured minus true log ratio; the true ratio of a
    chain is the sum of its links' true ratios, which telescopes to its two end clips')."""
    by_index = {s.run_index: s for s in links if s.consecutive}
    errors = []
    for k in by_index:
        chain = [by_index.get(k - i) for i in range(n)]
        if all(c is not None for c in chain):
            errors.append(sum(c.log_ratio - c.true_log_ratio for c in chain))
    return np.array(errors)


@dataclass(frozen=True)
class LinkScore:
    """links: scored; z_median: the median |error| / sigma of single links, within_2sigma their share within 2 sigma
    (both count the reference's own noise as the link's: an upper bound on a link's miscalibration);
    sigma_median: the links' median 1-sigma (relative); per_link_sd / reference_sd: from the chains' growth (module
    docstring), None with too few chains (or where the variance does not grow with n)."""

    links: int
    z_median: float | None
    within_2sigma: float | None
    sigma_median: float | None
    per_link_sd: float | None
    reference_sd: float | None

    @staticmethod
    def of(runs: Iterable[Sequence[ScoredLink]]) -> LinkScore:
        """The score of the links of one or several runs (chains never cross runs)."""
        runs = [list(r) for r in runs]
        every = [s for r in runs for s in r]
        if not every:
            return LinkScore(0, None, None, None, None, None)
        z = np.array([abs(s.log_ratio - s.true_log_ratio) / s.sigma for s in every])
        sd = None
        points = []
        for n in CHAIN_LENGTHS:
            e = np.concatenate([chain_errors(r, n) for r in runs])
            if len(e) >= MIN_CHAINS:
                points.append((n, _robust_var(e), len(e)))
        if len(points) >= 3:
            n, v, m = np.array(points).T
            # each variance weighted by its own precision: that of a variance from m errors is 2 v^2 / m, and chains
            # of n links overlap, so m of them hold about m / n independent ones
            w = np.sqrt(m / (2.0 * n)) / np.maximum(v, 1e-300)
            fit = np.linalg.lstsq(w[:, None] * np.c_[n, np.ones_like(n)], w * v, rcond=None)[0]
            if fit[0] > 0:
                sd = (math.sqrt(fit[0]), math.sqrt(max(fit[1], 0.0) / 2.0))
        return LinkScore(len(every), float(np.median(z)), float(np.mean(z <= 2.0)),
                         float(np.median([s.sigma for s in every])), *(sd if sd is not None else (None, None)))

    def as_dict(self) -> dict:
        """The JSON object ``link_errors`` (``vi3 eval``; docs/evaluation.md)."""
        return {"scored": self.links, "z_median": self.z_median, "within_2sigma": self.within_2sigma,
                "sigma_median": self.sigma_median, "per_link_sd": self.per_link_sd,
                "reference_sd": self.reference_sd}


__all__ = ["CHAIN_LENGTHS", "LinkScore", "ScoredLink", "chain_errors", "scored_links"]
