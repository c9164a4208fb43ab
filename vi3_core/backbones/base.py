"""The backbone contract: what every 3DFM adapter and the embedded ``classical`` backbone provide.

A backbone maps n undistorted images + intrinsics to a differentiable ``Prediction`` in one convention:
camera-to-world poses in OpenCV optical axes (x right, y down, z forward), world = first camera
(T_wc[0] = I at the base prediction), z-depth at the model resolution, confidence (higher is better).
Up-to-scale models are normalised the way their training normalised them; ``metric`` says otherwise.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field

import numpy as np
import torch

from vi3_core import so3
from vi3_core.preintegration import preintegrate
from vi3_core.types import Clip, Geometry, UnitsLink

#: Capabilities a backbone may declare.
CAP_TTR = "ttr"  # has trainable groups for test-time refinement
CAP_COND_POSE = "cond_pose"  # accepts metric camera poses as input conditioning (Pi3X, DA3)
CAP_COND_INTRINSICS = "cond_intrinsics"  # accepts intrinsics as conditioning (DA3)


@dataclass
class BackboneInputs:
    """Preprocessed model inputs.

    images: [n,3,h,w] float in [0,1], RGB, at the model resolution (h, w multiples of the patch size);
    K: [n,3,3] intrinsics at that resolution (rescaled/cropped consistently with the images);
    src_hw: (H, W) of the images given to ``preprocess``.
    """

    images: torch.Tensor
    K: torch.Tensor
    src_hw: tuple[int, int]


@dataclass
class Condition:
    """Metric input conditioning: T_wc [n,4,4] camera-to-world in the first camera frame (metres, float64
    numpy), optionally K [n,3,3] at the model resolution."""

    T_wc: np.ndarray
    K: np.ndarray | None = None


@dataclass
class Prediction:
    """Differentiable outputs (torch). R_wc [n,3,3]; t_wc [n,3] raw translation (model units, or metres
    when ``metric``); K [n,3,3]; depth [n,h,w] z-depth (> 0); conf [n,h,w] higher is better; traj_depth_sigma,
    units_link: ``Geometry``'s."""

    R_wc: torch.Tensor
    t_wc: torch.Tensor
    K: torch.Tensor
    depth: torch.Tensor
    conf: torch.Tensor
    metric: bool = False
    traj_depth_sigma: float = 0.0
    units_link: UnitsLink | None = None

    def geometry(self, scale: float = 1.0) -> Geometry:
        """Detached numpy ``Geometry`` with translation and depth multiplied by ``scale``."""
        # float32 rotations are 6e-8 from orthonormal: made rotations, since odom composes them without end
        R = so3.nearest_rotation(self.R_wc.detach().double().cpu().numpy())
        T = so3.make_T(R, self.t_wc.detach().double().cpu().numpy() * scale)
        return Geometry(T_wc=T, K=self.K.detach().double().cpu().numpy(),
                        depth=self.depth.detach().float().cpu().numpy() * scale,
                        conf=self.conf.detach().float().cpu().numpy(), metric=self.metric,
                        traj_depth_sigma=self.traj_depth_sigma, units_link=self.units_link)


@dataclass(frozen=True)
class GyroRotations:
    """A clip's camera rotations from its gyro, for a backbone that takes them (``Backbone.bind``): R_wc [n,3,3]
    camera i to the first camera (the backbone's world), integrated with the gyro bias estimate ``bg`` [3] rad/s of
    1-sigma ``bg_sigma`` rad/s (per axis); bias_jacobian [n,3,3] rad per rad/s in the first camera's frame,
    R_wc(bg + d) = Exp(bias_jacobian d) R_wc(bg); clock_sigma [n] rad, the 1-sigma each rotation has from the
    uncertainty of the IMU's clock against the frames' (a frame seen dt later turns by its rate change times dt)."""

    R_wc: np.ndarray
    bias_jacobian: np.ndarray
    bg: np.ndarray
    bg_sigma: float
    clock_sigma: np.ndarray

    @staticmethod
    def of(clip: Clip, bg: np.ndarray, bg_sigma: float, offset_sigma: float) -> GyroRotations:
        """From the clip's IMU (which must cover its stamps) through its mount, R_C1Ci = R_CB R_B1Bi R_BC, its clock
        good to ``offset_sigma`` s."""
        pre = preintegrate(clip.imu, clip.stamps, bg, jacobians=True)
        R_BC = np.asarray(clip.T_BC, np.float64)[:3, :3]
        rates = np.stack([np.interp(clip.stamps, clip.imu.t, clip.imu.gyro[:, j]) for j in range(3)], 1)
        clock = np.linalg.norm(rates - rates[0], axis=1) * offset_sigma
        return GyroRotations(R_BC.T @ pre.R @ R_BC, R_BC.T @ pre.J.phi_bg, np.asarray(bg, np.float64),
                             float(bg_sigma), clock)


@dataclass
class ParamGroups:
    """Trainable groups for TTR: the camera head, the depth head, and the global (inter-frame)
    attention blocks in network order (the last L of them are unfrozen by TTR)."""

    camera_head: list[torch.nn.Parameter] = field(default_factory=list)
    depth_head: list[torch.nn.Parameter] = field(default_factory=list)
    global_blocks: list[list[torch.nn.Parameter]] = field(default_factory=list)

    def trainable(self, last_blocks: int) -> list[torch.nn.Parameter]:
        """Camera head + depth head + the last ``last_blocks`` global blocks, without duplicates."""
        blocks = self.global_blocks[len(self.global_blocks) - last_blocks:] if last_blocks > 0 else []
        seen, out = set(), []
        for p in [*self.camera_head, *self.depth_head, *(p for b in blocks for p in b)]:
            if id(p) not in seen:
                seen.add(id(p))
                out.append(p)
        return out


class Backbone(abc.ABC):
    """A 3DFM (or the classical embedded pipeline) behind one interface.

    Subclasses set ``name``, ``metric``, ``capabilities``, ``patch_size`` and implement ``preprocess``,
    ``forward``, ``param_groups`` and ``modules`` (and ``diagnostics`` where they report on the clip). ``forward``
    must be differentiable with respect to the parameters returned by ``param_groups`` when gradients are enabled.
    """

    name: str = "abstract"
    metric: bool = False
    needs_images: bool = True  # False only for the evaluation's ground-truth instrument
    capabilities: frozenset[str] = frozenset()
    patch_size: int = 14
    #: AdamW learning rate TTR uses for this backbone's trainable groups unless AnchorOptions.lr is set.
    ttr_lr: float = 1e-5

    def __init__(self, *, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32) -> None:
        self.device = torch.device(device)
        self.dtype = dtype
        self.gradient_checkpointing = False

    @abc.abstractmethod
    def preprocess(self, images: np.ndarray, K: np.ndarray) -> BackboneInputs:
        """images [n,H,W] or [n,H,W,3] uint8 (undistorted), K [3,3] -> model inputs on ``device``."""

    @abc.abstractmethod
    def forward(self, inputs: BackboneInputs, condition: Condition | None = None) -> Prediction:
        """Differentiable prediction; ``condition`` only for backbones with a conditioning capability."""

    @abc.abstractmethod
    def param_groups(self) -> ParamGroups:
        """The trainable groups (see ``ParamGroups``)."""

    def modules(self) -> list[torch.nn.Module]:
        """The torch modules holding all parameters (put in eval mode; frozen except TTR groups)."""
        return []

    def bind(self, clip, *, depth_frames: np.ndarray | None = None, continued: bool = True,
             gyro: GyroRotations | None = None) -> None:
        """Called with each ``vi3_core.types.Clip`` just before it is predicted (``StreamEstimator``, with the
        configured calibration), for that prediction only; ``gyro``: its camera rotations from the gyro (on the clock
        and through the mount the rig's self-calibration applied), which the ``classical`` backbone's bundle
        adjustment takes as a prior. ``depth_frames``: the indices of the frames whose depth the
        caller reads (None: every frame); a backbone whose depth costs per frame may predict only those, the others
        NaN with zero confidence. Nothing for a model, which sees only its images and predicts every frame's depth in
        one pass; the evaluation's ground-truth instrument predicts from the clip's ground truth, and the
        ``classical`` backbone sweeps depth for ``depth_frames`` only. ``continued``: False when the clip must stand on
        its own (the independent evaluation, whose clips may run in any order or on other machines): nothing the
        backbone kept of earlier clips (the ``classical`` front end's tracks) may shape its prediction."""
        return

    def forget(self) -> None:
        """Drop what the backbone kept of earlier clips (the ``classical`` front end's tracks and carried structure):
        its next clip starts a new stream (``StreamEstimator``: a new one, or time went back). Without it, a clip whose
        stamps a previous stream's frames had (the same recording evaluated twice) would continue that stream's
        tracks. Nothing to drop for a model, which keeps nothing between clips."""
        return

    @property
    def exact_scale(self) -> float | None:
        """Metres per model unit of the last prediction where the backbone knows it exactly (the evaluation's
        ground-truth instrument), else None. The evaluation scores a claimed scale against it: a fit of positions
        would take the instrument's pose noise for scale error on a clip that barely moves."""
        return None

    def diagnostics(self) -> dict:
        """What the backbone reports about the last clip it preprocessed, as JSON-serialisable name -> value: keys
        ending in ``_s`` are stage timings in seconds; ``status`` and ``reason`` give the clip's outcome where the
        backbone has one. Empty by default (an adapter has nothing to report beyond its ``Prediction``)."""
        return {}

    def set_gradient_checkpointing(self, enabled: bool) -> None:
        """Trade recompute for memory in the trainable blocks (adapters override where upstream allows)."""
        self.gradient_checkpointing = enabled

    def predict_inputs(self, inputs: BackboneInputs, condition: Condition | None = None) -> Prediction:
        """``forward`` without gradients."""
        with torch.no_grad():
            return self.forward(inputs, condition)

    def predict(self, images: np.ndarray, K: np.ndarray, condition: Condition | None = None) -> Geometry:
        """One no-grad forward pass on raw images -> numpy ``Geometry``."""
        return self.predict_inputs(self.preprocess(images, K), condition).geometry()
