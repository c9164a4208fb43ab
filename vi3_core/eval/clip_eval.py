"""``ClipEval``: the evaluation record of one clip (what the runner produces and reports, plots and exports read)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vi3_core.eval.metrics import GeometryMetrics, InitMetrics
from vi3_core.online import OnlineDecision
from vi3_core.online.calibration import RigEstimate
from vi3_core.types import AnchorResult, Geometry, ImuTrajectory, InitResult


@dataclass
class ClipEval:
    """Evaluation of one clip.

    indices: [n] frame indices in the sequence; stamps: [n] s; status/reason: the init status and its reason;
    mode: the anchoring mode that actually ran ("none" when the init was not ok); T_gt: [n,4,4] GT camera poses
    in the first camera frame C1; down_c1: [3] unit gravity direction in C1 (from GT), for top-down views;
    init: the clip's initialisation; result: the final ``AnchorResult`` (None when the data checks rejected the clip
    before the backbone); fast: the fast init ``AnchorResult`` when mode is "cond"/"ttr"; columns:
    ``GeometryMetrics`` per column ("base", "init", and "cond"/"ttr" when run); init_metrics: errors of the
    initialisation against GT; decision: the online window's decision, with the clip's own initialisation (chained
    runs only); calibration: the rig's estimate after the clip (chained runs with self-calibration); exact_scale:
    metres per model unit of the clip's prediction where the backbone knew it exactly (``Backbone.exact_scale``: the
    ground-truth instrument), else None; backbone_diagnostics: what the backbone reported about the clip
    (``Backbone.diagnostics``, empty when it did not run).
    """

    indices: np.ndarray
    stamps: np.ndarray
    status: str
    reason: str
    mode: str
    T_gt: np.ndarray
    down_c1: np.ndarray
    init: InitResult
    result: AnchorResult | None
    fast: AnchorResult | None
    columns: dict[str, GeometryMetrics] = field(default_factory=dict)
    init_metrics: InitMetrics | None = None
    decision: OnlineDecision | None = None
    calibration: RigEstimate | None = None
    exact_scale: float | None = None
    backbone_diagnostics: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def base_lam(self) -> float:
        """Model units per metre of the clip's prediction against GT: 1 / ``exact_scale`` where the backbone knew it,
        else the base column's least-squares scale (NaN where there is none)."""
        if self.exact_scale:
            return 1.0 / self.exact_scale
        return self.columns["base"].scale_fit if "base" in self.columns else float("nan")

    @property
    def traj_depth_sigma(self) -> float | None:
        """The backbone's 1-sigma of the log of the clip's trajectory scale against its depth's (``Geometry``; 0: it
        does not say; None where the backbone did not run)."""
        return self.result.base.traj_depth_sigma if self.result is not None else None

    def trajectories(self) -> dict[str, np.ndarray]:
        """Camera trajectories [n,4,4] in C1 by name: "gt", "base", "imu" (the metric IMU target, when the
        init was ok), "init" (fast init result, when refined), "vi3" (the final metric output, when ok); only "gt"
        when the backbone did not run."""
        if self.result is None:
            return {"gt": self.T_gt}
        out = {"gt": self.T_gt, "base": self.result.base.T_wc}
        target: ImuTrajectory | None = self.result.target or self.init.target
        if target is not None:
            out["imu"] = target.T_wc
        if self.ok:
            if self.fast is not None:
                out["init"] = self.fast.geometry.T_wc
            out["vi3"] = self.result.geometry.T_wc
        return out

    def vi3_geometry(self) -> Geometry | None:
        """The final metric geometry, or None when the init was not ok."""
        return self.result.geometry if self.ok else None
