"""The scale links scored against the ground truth (``vi3_core.eval.links``)."""

from __future__ import annotations

import math

import numpy as np

from vi3_core.eval.links import LinkScore, chain_errors, scored_links


def _run(rng: np.random.Generator, n: int, *, walk: float, link_sd: float, ref_sd: float, sigma: float):
    """A run of n clips 0.5 s apart whose true scale walks by ``walk`` per clip; each clip links to the one before
    with an error of ``link_sd`` and claims ``sigma``; the ground truth's per-clip scale is off by ``ref_sd``."""
    log_lam = np.cumsum(rng.normal(0.0, walk, n))
    t0 = 100.0 + 0.5 * np.arange(n)
    links = [None] + [(log_lam[k] - log_lam[k - 1] + rng.normal(0.0, link_sd), sigma, t0[k - 1]) for k in range(1, n)]
    base = np.exp(log_lam + rng.normal(0.0, ref_sd, n))
    return scored_links(t0, links, base)


def test_chains_separate_the_links_errors_from_the_ground_truths_own():
    rng = np.random.default_rng(0)
    runs = [_run(rng, 300, walk=0.04, link_sd=0.02, ref_sd=0.05, sigma=0.02) for _ in range(3)]
    score = LinkScore.of(runs)
    assert score.links == 3 * 299
    # a single link's error mixes in the ground truth's noise at both ends: sd 0.073 against the link's 0.02
    assert score.z_median > 2.0 and score.within_2sigma < 0.6, score
    assert math.isclose(score.per_link_sd, 0.02, rel_tol=0.3), score
    assert math.isclose(score.reference_sd, 0.05, rel_tol=0.15), score
    assert math.isclose(score.sigma_median, 0.02)
    # the errors of chains of n links grow as n link variances plus two of the ground truth's
    e1, e8 = (np.concatenate([chain_errors(r, n) for r in runs]) for n in (1, 8))
    assert np.std(e8) ** 2 - np.std(e1) ** 2 > 4 * 0.02**2


def test_an_honest_link_with_an_exact_ground_truth_is_within_its_sigma():
    rng = np.random.default_rng(1)
    score = LinkScore.of([_run(rng, 400, walk=0.04, link_sd=0.01, ref_sd=0.0, sigma=0.01)])
    assert 0.55 < score.z_median < 0.8 and 0.93 < score.within_2sigma < 0.98, score
    assert math.isclose(score.per_link_sd, 0.01, rel_tol=0.2) and score.reference_sd < 0.003, score


def test_links_are_matched_to_the_clip_they_name_and_unscorable_ones_left_out():
    t0 = [10.0, 10.5, 11.0, 11.5]
    base = [2.0, 2.2, np.nan, 2.42]
    links = [None, (math.log(1.1), 0.01, 10.0),  # clip 1 -> 0: true ratio 1.1
             (0.0, 0.01, 10.5),  # clip 2 has no ground truth
             (math.log(1.1), 0.02, 10.5)]  # clip 3 across the dropped clip 2 -> clip 1
    scored = scored_links(t0, links, base)
    assert [(s.run_index, s.consecutive) for s in scored] == [(1, True), (3, False)]
    assert all(abs(s.log_ratio - s.true_log_ratio) < 1e-12 for s in scored)
    assert scored_links(t0, [None, (0.0, 0.01, 10.2), None, None], base) == []  # names no clip of the run
    assert LinkScore.of([[]]).links == 0 and LinkScore.of([scored]).per_link_sd is None  # no chains to fit
