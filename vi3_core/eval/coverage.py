"""How soon and how often a chained run claims a scale once the vehicle moves (the product's second promise: metric
output as soon and as often as the motion allows), and what became of its scale links.

Motion starts at the first ground-truth stamp, from the first clip on, at which the body's speed reaches
``MOTION_SPEED``; a clip is in flight when it starts ``IN_FLIGHT_AFTER_S`` or more after that. The time to the first
claim is from the start of motion to the last frame of the first claimed clip (the earliest a claim can be made).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

MOTION_SPEED = 0.1  # m/s: slower is standing, hovering or ground-truth noise
IN_FLIGHT_AFTER_S = 5.0  # s after the start of motion: the clips the share of claims counts


@dataclass(frozen=True)
class Coverage:
    """motion_start: s (stamp), NaN when the ground truth never reaches MOTION_SPEED; first_claim_s: s from it to the
    last frame of the first claimed clip (None: no claim); in_flight_clips / in_flight_claimed: the clips that start
    IN_FLIGHT_AFTER_S or more after it, and how many of them were claimed; links_accepted / links_rejected /
    links_none: the clips that joined the window with a scale link the fit used, with one it refused, or with none."""

    motion_start: float
    first_claim_s: float | None
    in_flight_clips: int
    in_flight_claimed: int
    links_accepted: int
    links_rejected: int
    links_none: int

    def as_dict(self) -> dict:
        share = self.in_flight_claimed / self.in_flight_clips if self.in_flight_clips else None
        return {"first_claim_after_motion_s": self.first_claim_s,
                "in_flight": {"clips": self.in_flight_clips, "claimed": self.in_flight_claimed, "share": share},
                "links": {"accepted": self.links_accepted, "rejected": self.links_rejected,
                          "none": self.links_none}}


def motion_start(t: np.ndarray, v_W: np.ndarray, t0: float) -> float:
    """The first stamp of ``t`` [M] s at or after ``t0`` at which the speed |v_W| [M,3] (m/s) reaches MOTION_SPEED
    (NaN when it never does)."""
    moving = (t >= t0) & (np.linalg.norm(v_W, axis=1) >= MOTION_SPEED)
    return float(t[np.argmax(moving)]) if moving.any() else float("nan")


def coverage(t0: np.ndarray, t1: np.ndarray, claimed: np.ndarray, links: Iterable[str], start: float) -> Coverage:
    """The coverage of clips spanning [t0, t1] [n] s, ``claimed`` [n] bool, with link states ``links`` [n] ("linked",
    "rejected", "none", or "" for a clip that did not join the window), for motion starting at ``start`` s."""
    t0, t1, claimed = np.asarray(t0, float), np.asarray(t1, float), np.asarray(claimed, bool)
    after = claimed & (t1 >= start) if np.isfinite(start) else np.zeros(len(t0), bool)
    first = float(t1[np.argmax(after)] - start) if after.any() else None
    flying = t0 >= start + IN_FLIGHT_AFTER_S if np.isfinite(start) else np.zeros(len(t0), bool)
    links = list(links)
    return Coverage(start, first, int(flying.sum()), int((flying & claimed).sum()), links.count("linked"),
                    links.count("rejected"), links.count("none"))


def pool(coverages: Iterable[Coverage]) -> dict:
    """Several sequences' coverage: clips and claims in flight and links summed, the latest first claim."""
    cs = list(coverages)
    firsts = [c.first_claim_s for c in cs if c.first_claim_s is not None]
    total = Coverage(float("nan"), max(firsts) if firsts else None, sum(c.in_flight_clips for c in cs),
                     sum(c.in_flight_claimed for c in cs), sum(c.links_accepted for c in cs),
                     sum(c.links_rejected for c in cs), sum(c.links_none for c in cs))
    out = total.as_dict()
    out["first_claim_after_motion_s_max"] = out.pop("first_claim_after_motion_s")
    return out


__all__ = ["IN_FLIGHT_AFTER_S", "MOTION_SPEED", "Coverage", "coverage", "motion_start", "pool"]
