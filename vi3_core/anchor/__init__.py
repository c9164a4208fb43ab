"""Metric anchoring of a backbone's geometry with the IMU: ``anchor(clip, backbone, mode=...)`` for the modes
init (scale only), cond (input conditioning) and ttr (test-time refinement)."""

from vi3_core.anchor.anchor import anchor, check_mode
from vi3_core.anchor.options import MODES, AnchorOptions

__all__ = ["MODES", "AnchorOptions", "anchor", "check_mode"]
