"""Online metric state across clips (beyond the paper): a joint fit of the clips of the last seconds (``window``),
priors from the odom state with their consistency tests, restarts, and the chaining of the clips into one
continuous, gravity-aligned odom trajectory (REP-105)."""

from vi3_core.online.chain import ChainedClip, Trajectory, gravity_align
from vi3_core.online.estimator import OdomState, OnlineDecision, OnlineEstimator
from vi3_core.online.options import OnlineOptions

__all__ = ["ChainedClip", "OdomState", "OnlineDecision", "OnlineEstimator", "OnlineOptions", "Trajectory",
           "gravity_align"]
