"""``AnchorOptions``: the knobs of metric anchoring and test-time refinement (TTR)."""

from __future__ import annotations

from dataclasses import dataclass

MODES = ("init", "cond", "ttr")


@dataclass(frozen=True)
class AnchorOptions:
    """Paper defaults (Sec. "Experimental setup"): K = 160 AdamW steps, w_r = 20, w_p = 10, w_d = 10,
    w_ap = 1000, w_ad = 1, the camera and depth heads plus the last L = 8 global blocks and alpha trainable.

    lr: learning rate of the backbone's trainable groups (None: the backbone's ``ttr_lr``);
    lr_alpha: learning rate of log alpha; weight_decay: AdamW's, never applied to alpha;
    dcons_stride: pixel subsampling of Eq. dcons's target frames (4: every 16th pixel, an unbiased estimate of
    the same mean at 1/16 of the cost); seed: torch seed for a deterministic run;
    geocalib: use GeoCalib as a gravity seed when it is installed.
    """

    ttr_steps: int = 160
    lr: float | None = None
    lr_alpha: float = 3e-3
    weight_decay: float = 0.01
    w_rot: float = 20.0
    w_pos: float = 10.0
    w_dcons: float = 10.0
    w_anchor_pos: float = 1000.0
    w_anchor_depth: float = 1.0
    last_blocks: int = 8
    dcons_stride: int = 4
    gradient_checkpointing: bool = False
    seed: int = 0
    geocalib: bool = False

    def __post_init__(self) -> None:
        if self.ttr_steps < 0 or self.last_blocks < 0 or self.dcons_stride < 1:
            raise ValueError("ttr_steps and last_blocks must be >= 0 and dcons_stride >= 1")
