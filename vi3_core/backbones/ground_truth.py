"""The ground-truth pose instrument for controlled experiments (``vi3 eval --backbone gt --gt-noise POS_M,ROT_DEG
--gt-depth-noise REL,SMOOTH``): a clip's true camera poses at an arbitrary model scale with a stated noise
(``sim.visual.PoseNoise``), and its true depth, where the recording has it, at the same model scale with a stated noise
(``sim.visual.DepthNoise``). It needs the clip's ground truth, so it exists only in the evaluation (the runner
binds each clip to it): it is an evaluation instrument, never a backbone for the node or replay. It needs no images,
so it runs on recordings of IMU and ground truth alone.

The model scale of each clip is chosen as a 3DFM normalises a clip: the mean distance of its cameras from the first
is one model unit; noise is drawn per frame (the first included, then re-anchored at the first frame) from a
generator seeded by ``seed`` and the clip's first stamp, so a clip gets the same noise in every run, and two clips that
share a frame predict it with independent errors, as two passes of a 3DFM would.
"""

from __future__ import annotations

import numpy as np
import torch

from vi3_core import so3
from vi3_core.backbones.base import Backbone, BackboneInputs, Condition, GyroRotations, ParamGroups, Prediction
from vi3_core.dataset.sequence import gt_camera_poses
from vi3_core.errors import DataError
from vi3_core.sim.visual import DepthNoise, PoseNoise, noisy_poses
from vi3_core.types import Clip


class GroundTruthPoses(Backbone):
    """Noisy ground-truth poses of the bound clip (``bind``); init mode only."""

    name = "gt"
    needs_images = False

    def __init__(self, *, noise: PoseNoise | None = None, depth_noise: DepthNoise | None = None, seed: int = 0,
                 mount_error: np.ndarray | None = None, device: str = "cpu",
                 dtype: torch.dtype = torch.float32) -> None:
        super().__init__(device=device, dtype=dtype)
        self.noise, self.depth_noise, self.seed = noise or PoseNoise(), depth_noise or DepthNoise(), int(seed)
        # rad [3]: the camera's true mount is the configured one (the clip's T_BC) turned by Exp(mount_error)
        self.mount_error = np.zeros(3) if mount_error is None else np.asarray(mount_error, np.float64)
        self._clip: Clip | None = None
        self.last_scale = float("nan")  # metres per model unit of the last prediction (the truth a scale estimates)

    @property
    def exact_scale(self) -> float | None:
        return None if np.isnan(self.last_scale) else self.last_scale

    def bind(self, clip: Clip, *, depth_frames: np.ndarray | None = None, continued: bool = True,
             gyro: GyroRotations | None = None) -> None:
        """The clip whose ground truth the next prediction uses (the stream binds each clip as it processes it, with
        the configured calibration); its depth is that of every frame whatever ``depth_frames`` says."""
        if clip.gt is None:
            raise DataError(f"the gt instrument needs ground truth for the clip at {clip.stamps[0]:.6f} s")
        self._clip = clip

    def preprocess(self, images: np.ndarray, K: np.ndarray) -> BackboneInputs:
        if self._clip is None:
            raise DataError("the gt instrument predicts only clips bound to it (vi3 eval --backbone gt)")
        n = self._clip.n
        return BackboneInputs(images=torch.zeros((n, 3, 0, 0)), K=torch.as_tensor(np.repeat(K[None], n, 0)),
                              src_hw=(0, 0))

    def forward(self, inputs: BackboneInputs, condition: Condition | None = None) -> Prediction:
        clip = self._clip
        T_BC = so3.turn_T(clip.T_BC, self.mount_error)
        T_gt = gt_camera_poses(clip.gt, T_BC)
        dist = float(np.linalg.norm(T_gt[:, :3, 3], axis=1).mean())
        scale = self.last_scale = dist if dist > 0 else 1.0  # metres per model unit
        rng = np.random.default_rng([self.seed, int(round(float(clip.stamps[0]) * 1e6))])
        T = noisy_poses(T_gt, scale=scale, noise=self.noise, rng=rng)
        if clip.gt.depth is not None:
            depth = self.depth_noise.apply(np.asarray(clip.gt.depth, np.float32) / np.float32(scale), rng)
        else:
            depth = np.full((clip.n, 1, 1), np.nan, np.float32)
        return Prediction(R_wc=torch.as_tensor(T[:, :3, :3]), t_wc=torch.as_tensor(T[:, :3, 3]), K=inputs.K.double(),
                          depth=torch.as_tensor(depth, dtype=torch.float32), conf=torch.ones(depth.shape),
                          metric=False)

    def param_groups(self) -> ParamGroups:
        return ParamGroups()
