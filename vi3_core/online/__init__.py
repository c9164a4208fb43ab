"""Online metric state across clips (beyond the paper): a joint fit of the clips of the last seconds (``window``),
priors from the odom state with their consistency tests, restarts, the chaining of the clips into one continuous,
gravity-aligned odom trajectory (REP-105), IMU-rate propagation between clips, and ``StreamEstimator``, the one
per-clip loop of a stream that the node, replay and the evaluation drive."""

from vi3_core.online.chain import ChainedClip, OdomChain, OdomState, Trajectory, gravity_align
from vi3_core.online.estimator import OnlineDecision, OnlineEstimator
from vi3_core.online.options import OnlineOptions
from vi3_core.online.stream import ClipOutcome, InOdom, StreamEstimator, StreamOptions

__all__ = ["ChainedClip", "ClipOutcome", "InOdom", "OdomChain", "OdomState", "OnlineDecision", "OnlineEstimator",
           "OnlineOptions", "StreamEstimator", "StreamOptions", "Trajectory", "gravity_align"]
