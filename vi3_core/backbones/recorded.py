"""A backbone's predictions recorded clip by clip and served again: for measuring what the pipeline costs beside its
backbone (``vi3 bench pipeline``), as a GPU model's node would run with the backbone's time taken out.

``RecordingBackbone`` runs a real backbone and keeps the base prediction of every clip it is bound to (its frames'
stamps are the key); ``RecordedBackbone`` then answers each of those clips with that prediction and no work. Like the
evaluation's ground-truth instrument it is a measuring tool, not a model: it knows only the clips it was shown, and
a clip it was not shown is a DataError.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from vi3_core.backbones.base import Backbone, BackboneInputs, Condition, GyroRotations, ParamGroups, Prediction
from vi3_core.errors import DataError, ModeNotSupported


def clip_key(clip) -> tuple:
    """A ``vi3_core.types.Clip``'s identity: its frames' stamps (ns where known, else s)."""
    return tuple((clip.stamps_ns if clip.stamps_ns is not None else clip.stamps).tolist())


@dataclass
class Recording:
    """The base predictions (detached) and the backbone's diagnostics of each clip, by ``clip_key``."""

    predictions: dict[tuple, Prediction] = field(default_factory=dict)
    diagnostics: dict[tuple, dict] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.predictions)


class RecordingBackbone(Backbone):
    """``inner``, unchanged, keeping each bound clip's base prediction (a forward without condition or gradients) in
    ``recording``."""

    def __init__(self, inner: Backbone, recording: Recording) -> None:
        super().__init__(device=inner.device, dtype=inner.dtype)
        self.inner, self.recording = inner, recording
        self.name, self.metric, self.capabilities = inner.name, inner.metric, inner.capabilities
        self.patch_size, self.needs_images = inner.patch_size, inner.needs_images
        self._key: tuple | None = None

    def bind(self, clip, *, depth_frames: np.ndarray | None = None, continued: bool = True,
             gyro: GyroRotations | None = None) -> None:
        self._key = clip_key(clip)
        self.inner.bind(clip, depth_frames=depth_frames, continued=continued, gyro=gyro)

    def forget(self) -> None:
        self.inner.forget()

    def preprocess(self, images: np.ndarray, K: np.ndarray) -> BackboneInputs:
        return self.inner.preprocess(images, K)

    def forward(self, inputs: BackboneInputs, condition: Condition | None = None) -> Prediction:
        pred = self.inner.forward(inputs, condition)
        if condition is None and not torch.is_grad_enabled() and self._key is not None:
            self.recording.predictions[self._key] = Prediction(*(t.detach().clone() for t in (
                pred.R_wc, pred.t_wc, pred.K, pred.depth, pred.conf)), metric=pred.metric,
                traj_depth_sigma=pred.traj_depth_sigma, units_link=pred.units_link)
            self.recording.diagnostics[self._key] = self.inner.diagnostics()
        return pred

    def param_groups(self) -> ParamGroups:
        return self.inner.param_groups()

    def modules(self) -> list[torch.nn.Module]:
        return self.inner.modules()

    def diagnostics(self) -> dict:
        return self.inner.diagnostics()


class RecordedBackbone(Backbone):
    """Answers each clip of ``recording`` with its recorded prediction (init mode only: no conditioning, nothing to
    refine)."""

    def __init__(self, recording: Recording, *, name: str = "recorded") -> None:
        super().__init__()
        self.recording, self.name = recording, name
        self._key: tuple | None = None

    def bind(self, clip, *, depth_frames: np.ndarray | None = None, continued: bool = True,
             gyro: GyroRotations | None = None) -> None:
        self._key = clip_key(clip)

    def preprocess(self, images: np.ndarray, K: np.ndarray) -> BackboneInputs:
        pred = self.recording.predictions.get(self._key)
        if pred is None:
            raise DataError(f"the recording has no prediction of the clip with frames at {self._key}")
        return BackboneInputs(images=torch.empty(0), K=pred.K, src_hw=tuple(images.shape[1:3]))

    def forward(self, inputs: BackboneInputs, condition: Condition | None = None) -> Prediction:
        if condition is not None:
            raise ModeNotSupported("a recorded backbone takes no conditioning")
        return self.recording.predictions[self._key]

    def param_groups(self) -> ParamGroups:
        return ParamGroups()

    def diagnostics(self) -> dict:
        return dict(self.recording.diagnostics.get(self._key, {}))


__all__ = ["Recording", "RecordedBackbone", "RecordingBackbone", "clip_key"]
