"""Shared plumbing of the backbones: lazy upstream imports, checkpoint resolution (local path or the Hugging Face
cache, offline-capable), weight loading, preprocessing to the working grid (also the classical backbone's),
pose re-anchoring, mixed precision for the VGGT-family trunks, and the metric-scale restoration after pose
conditioning.

Nothing here imports an upstream model package at module import time.
"""

from __future__ import annotations

import abc
import contextlib
import importlib
import math
import os
from pathlib import Path
from types import ModuleType

import numpy as np
import torch
import torch.nn.functional as F

from vi3_core import so3
from vi3_core.backbones.base import (
    CAP_COND_INTRINSICS,
    CAP_COND_POSE,
    Backbone,
    BackboneInputs,
    Condition,
    Prediction,
)
from vi3_core.errors import BackboneUnavailable, CalibrationError, DataError, ModeNotSupported

#: Weight files tried, in order, inside a checkpoint directory.
WEIGHT_FILES = ("model.safetensors", "model.pt", "pytorch_model.bin")


def require(module: str, *, backbone: str, install: str) -> ModuleType:
    """Import an upstream module or raise ``BackboneUnavailable`` naming the install command."""
    try:
        return importlib.import_module(module)
    except ImportError as err:
        raise BackboneUnavailable(
            f"backbone {backbone!r} needs the upstream package providing {module!r}, which is not importable "
            f"({err}); install it with: {install}") from err


def hf_hub_cache() -> Path:
    """The Hugging Face hub cache folder, read from HF_HUB_CACHE / HF_HOME at call time."""
    return Path(os.environ.get("HF_HUB_CACHE") or os.path.join(
        os.environ.get("HF_HOME", os.path.join(os.path.expanduser("~"), ".cache", "huggingface")), "hub"))


def hf_cache_dir(repo_id: str) -> Path:
    """Where the Hugging Face cache keeps ``repo_id``."""
    return hf_hub_cache() / ("models--" + repo_id.replace("/", "--"))


def resolve_checkpoint(checkpoint: str | os.PathLike, *, backbone: str,
                       weight_files: tuple[str, ...] = WEIGHT_FILES) -> Path:
    """The weight file for ``checkpoint``: an existing local file, a local directory holding one of
    ``weight_files``, or a Hugging Face repo id found in the cache (downloaded only when the hub is online,
    i.e. HF_HUB_OFFLINE is unset). Raises ``BackboneUnavailable`` naming the expected location otherwise."""
    path = Path(checkpoint).expanduser()
    if path.is_file():
        return path
    if path.is_dir():
        return _weight_file_in(path, backbone=backbone, weight_files=weight_files)
    repo_id = str(checkpoint)
    if repo_id.count("/") != 1 or repo_id.startswith((".", "/", "~")):
        raise BackboneUnavailable(f"backbone {backbone!r}: checkpoint {repo_id!r} is neither an existing file or "
                                  f"directory nor a Hugging Face repo id of the form 'org/name'")
    hub = require("huggingface_hub", backbone=backbone, install="pip install huggingface_hub")
    offline = os.environ.get("HF_HUB_OFFLINE", "0").strip().lower() in {"1", "true", "yes", "on"}
    try:
        snapshot = hub.snapshot_download(repo_id, allow_patterns=[*weight_files, "config.json"],
                                         cache_dir=hf_hub_cache(), local_files_only=offline)
    except Exception as err:  # LocalEntryNotFound, gated repo, no network: all mean "not available here"
        raise BackboneUnavailable(
            f"backbone {backbone!r}: checkpoint {repo_id!r} is not in the Hugging Face cache at "
            f"{hf_cache_dir(repo_id)} ({type(err).__name__}: {err}); fetch it on a connected machine with "
            f"`hf download {repo_id}` (or pass checkpoint=<local file or directory>)") from err
    return _weight_file_in(Path(snapshot), backbone=backbone, weight_files=weight_files)


def _weight_file_in(directory: Path, *, backbone: str, weight_files: tuple[str, ...]) -> Path:
    for name in weight_files:
        if (directory / name).is_file():
            return directory / name
    raise BackboneUnavailable(f"backbone {backbone!r}: checkpoint directory {directory} holds none of "
                              f"{', '.join(weight_files)}")


def load_weights(module: torch.nn.Module, weight_file: Path, *, backbone: str, strip_prefix: str = "") -> None:
    """Load a safetensors or torch state dict into ``module`` (strict). ``strip_prefix`` is removed from
    keys that carry it (checkpoints saved from an upstream wrapper around the network)."""
    if weight_file.suffix == ".safetensors":
        state = require("safetensors.torch", backbone=backbone, install="pip install safetensors").load_file(
            str(weight_file), device="cpu")
    else:
        state = torch.load(weight_file, map_location="cpu", weights_only=True)
        state = state.get("model", state) if isinstance(state, dict) else state
    if strip_prefix:
        state = {k.removeprefix(strip_prefix): v for k, v in state.items()}
    try:
        module.load_state_dict(state, strict=True)
    except RuntimeError as err:
        raise BackboneUnavailable(f"backbone {backbone!r}: weights in {weight_file} do not match the "
                                  f"architecture: {err}") from err


def hw_fixed_width(H: int, W: int, *, width: int, patch: int) -> tuple[int, int]:
    """VGGT's rule: width ``width``, height scaled with the aspect ratio to a patch multiple, capped at
    ``width`` (the excess is centre-cropped)."""
    h = max(patch, round(H * width / W / patch) * patch)
    return min(h, width), width


def hw_pixel_budget(H: int, W: int, *, pixels: int, patch: int, strict: bool) -> tuple[int, int]:
    """Patch grid closest to ``pixels`` pixels at the image's aspect ratio. ``strict`` shrinks the grid
    until it fits within the budget (pi3), otherwise rounding may exceed it slightly (VGGT-Omega)."""
    s = math.sqrt(pixels / (H * W))
    k, m = max(1, round(W * s / patch)), max(1, round(H * s / patch))
    while strict and k * m * patch * patch > pixels and k * m > 1:
        if k / W >= m / H:
            k -= 1
        else:
            m -= 1
    return m * patch, k * patch


def hw_long_side(H: int, W: int, *, long_side: int, patch: int) -> tuple[int, int]:
    """DA3's rule: longest side ``long_side``, each side rounded to a patch multiple."""
    s = long_side / max(H, W)
    return max(patch, round(H * s / patch) * patch), max(patch, round(W * s / patch) * patch)


def check_clip(images: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The input checks of every backbone's ``preprocess``: images [n,H,W] or [n,H,W,3] uint8 with n >= 1 and a
    finite K [3,3] (pixels) with fx, fy > 0. Returns (images, K as float64); raises ``DataError`` /
    ``CalibrationError`` naming what is wrong."""
    images = np.asarray(images)
    if images.dtype != np.uint8 or images.ndim not in (3, 4) or (images.ndim == 4 and images.shape[3] != 3) \
            or images.shape[0] < 1:
        raise DataError(f"images must be uint8 [n,H,W] or [n,H,W,3] with n >= 1; got {images.dtype} {images.shape}")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError(f"K must be a finite [3,3] intrinsic matrix with fx, fy > 0; got {K.tolist()}")
    return images, K


def resize_crop(images: np.ndarray, K: np.ndarray, hw: tuple[int, int], *,
                device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Uniformly scale ``images`` [n,H,W(,3)] uint8 so they cover ``hw`` = (h, w) and centre-crop to it; ``images``
    and ``K`` [3,3] (pixels) as returned by ``check_clip``.

    Returns images [n,3,h,w] float32 in [0,1] on ``device`` (grey replicated to RGB; bilinear, antialiased when
    shrinking) and K [n,3,3] float32 for the new pixel grid (``scaled_K``)."""
    x = torch.from_numpy(np.ascontiguousarray(images)).to(device)
    x = x[:, None] if x.ndim == 3 else x.permute(0, 3, 1, 2)  # grey stays one channel until after the resize
    x = x.float() / 255.0
    n, _, H, W = x.shape
    h, w = hw
    s = max(h / H, w / W)
    Hs, Ws = max(h, round(H * s)), max(w, round(W * s))
    x = F.interpolate(x, size=(Hs, Ws), mode="bilinear", align_corners=False, antialias=Hs < H)
    top, left = (Hs - h) // 2, (Ws - w) // 2
    x = x[:, :, top:top + h, left:left + w].clamp(0.0, 1.0).expand(n, 3, h, w)
    Kn = scaled_K(K, Ws / W, Hs / H, left=left, top=top)
    Kt = torch.as_tensor(Kn, dtype=torch.float32, device=device).expand(n, 3, 3).clone()
    return x.contiguous(), Kt


def scaled_K(K: np.ndarray, sx: float, sy: float, *, left: int = 0, top: int = 0) -> np.ndarray:
    """K [3,3] (pixels) of an image scaled by ``sx`` x ``sy`` and then cropped ``left`` / ``top`` pixels: the focal
    lengths and skew scale with the image, the principal point follows the pixel-centre convention
    u' = (u + 0.5) * s - 0.5 - crop offset."""
    return np.array([[K[0, 0] * sx, K[0, 1] * sx, (K[0, 2] + 0.5) * sx - 0.5 - left],
                     [0.0, K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5 - top],
                     [0.0, 0.0, 1.0]])


def anchor_c2w(R_wc: torch.Tensor, t_wc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Re-express camera-to-world poses [n,3,3], [n,3] in the first camera's frame (frame 0 = identity)."""
    R0t = R_wc[0].transpose(-1, -2)
    return R0t @ R_wc, (t_wc - t_wc[0]) @ R0t.transpose(-1, -2)


def anchor_w2c(R_cw: torch.Tensor, t_cw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World-to-camera extrinsics [n,3,3], [n,3] -> camera-to-world in the first camera's frame."""
    R_wc = R_cw.transpose(-1, -2)
    return anchor_c2w(R_wc, -(R_wc @ t_cw[..., None])[..., 0])


def fit_metric_scale(t_pred: torch.Tensor, t_cond: torch.Tensor, *, fallback: float) -> torch.Tensor:
    """Scale (detached scalar) mapping predicted camera centres [n,3] (model units, frame 0 at the origin)
    onto the metric conditioning centres [n,3]: argmin_s sum ||s t_pred - t_cond||^2. With no baseline
    (both centre sets ~0) the scale is the model's input normalisation factor ``fallback``."""
    num = (t_pred.detach() * t_cond).sum()
    den = (t_pred.detach() ** 2).sum()
    if float(den) < 1e-12 or float((t_cond ** 2).sum()) < 1e-12:
        return torch.as_tensor(fallback, dtype=t_pred.dtype, device=t_pred.device)
    return num / den


def prediction(R_wc: torch.Tensor, t_wc: torch.Tensor, K: torch.Tensor, depth: torch.Tensor, conf: torch.Tensor, *,
               cond_centres: torch.Tensor | None = None, fallback: float = 1.0) -> Prediction:
    """An adapter's ``Prediction`` from frame-0-anchored poses R_wc [n,3,3], t_wc [n,3], K [n,3,3] (pixels),
    z-depth and confidence [n,h,w].

    Without ``cond_centres`` it is up to scale (``metric=False``). With the metric condition camera centres
    cond_centres [n,3] (metres, frame 0 at the origin), translations and depth are multiplied by
    ``fit_metric_scale(t_wc, cond_centres, fallback=fallback)`` and the prediction is in metres (``metric=True``);
    ``fallback`` is the factor by which the model normalised the condition translations."""
    if cond_centres is None:
        return Prediction(R_wc=R_wc, t_wc=t_wc, K=K, depth=depth, conf=conf, metric=False)
    s = fit_metric_scale(t_wc, cond_centres, fallback=fallback)
    return Prediction(R_wc=R_wc, t_wc=t_wc * s, K=K, depth=depth * s, conf=conf, metric=True)


def autocast(device: torch.device, dtype: torch.dtype) -> contextlib.AbstractContextManager:
    """Mixed precision for the transformer trunk when ``dtype`` is not float32 (heads stay float32)."""
    if dtype == torch.float32:
        return contextlib.nullcontext()
    return torch.autocast(device_type=device.type, dtype=dtype)


def aggregate(aggregator: torch.nn.Module, images: torch.Tensor, *, device: torch.device,
              dtype: torch.dtype) -> tuple[list[torch.Tensor | None], int]:
    """Run a VGGT or VGGT-Omega aggregator on images [1,n,3,h,w] in [0,1] under ``autocast(device, dtype)``.

    Returns its per-layer tokens [1,n,T,2C] as float32 (None for the layers VGGT-Omega does not cache) and the
    index of the first patch token. The caller runs the heads outside autocast on these float32 tokens, as
    upstream's ``VGGT.forward`` / ``VGGTOmega.forward`` run them with autocast disabled: VGGT-Omega's heads cast
    their inputs to float32 themselves, VGGT's do not (its DPT head fails on bfloat16 tokens), so the cast here
    gives both the inputs their weights expect whatever precision autocast leaves the tokens in."""
    with autocast(device, dtype):
        tokens, patch_start = aggregator(images)
    return [None if t is None else t.float() for t in tokens], patch_start


def freeze(module: torch.nn.Module) -> None:
    """Eval mode and no gradients for every parameter (TTR re-enables its own groups)."""
    module.eval()
    for p in module.parameters():
        p.requires_grad_(False)


def params(*modules: torch.nn.Module) -> list[torch.nn.Parameter]:
    """All parameters of ``modules`` in order."""
    return [p for m in modules for p in m.parameters()]


def intrinsics_from_rays(xy: torch.Tensor) -> torch.Tensor:
    """Pinhole K [n,3,3] implied by per-pixel normalised coordinates ``xy`` [n,h,w,2] (X/Z, Y/Z), for
    models that predict camera-frame points but no intrinsics (pi3, Pi3X). The principal point is the image
    centre; each focal length is the least-squares fit of u - cx = fx * X/Z (resp. v, fy)."""
    n, h, w, _ = xy.shape
    u = torch.arange(w, device=xy.device, dtype=xy.dtype) - (w - 1) / 2
    v = torch.arange(h, device=xy.device, dtype=xy.dtype) - (h - 1) / 2
    fx = (xy[..., 0] * u).sum((1, 2)) / (xy[..., 0] ** 2).sum((1, 2)).clamp_min(1e-12)
    fy = (xy[..., 1] * v[:, None]).sum((1, 2)) / (xy[..., 1] ** 2).sum((1, 2)).clamp_min(1e-12)
    K = torch.zeros(n, 3, 3, device=xy.device, dtype=xy.dtype)
    K[:, 0, 0], K[:, 1, 1] = fx, fy
    K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = (w - 1) / 2, (h - 1) / 2, 1.0
    return K


class UpstreamBackbone(Backbone):
    """Common part of the 3DFM adapters: the upstream network ``net`` (frozen, eval mode, on ``device``),
    preprocessing to the model's patch grid, and ``modules``. Subclasses build ``net`` and implement
    ``target_hw``, ``forward`` and ``param_groups``."""

    net: torch.nn.Module

    def install_net(self, net: torch.nn.Module) -> None:
        """Move the built (and loaded) network to ``device`` in float32 and freeze it."""
        self.net = net.to(device=self.device, dtype=torch.float32)
        freeze(self.net)

    @abc.abstractmethod
    def target_hw(self, H: int, W: int) -> tuple[int, int]:
        """Model input size (h, w), multiples of ``patch_size``, for an H x W source image."""

    def preprocess(self, images: np.ndarray, K: np.ndarray) -> BackboneInputs:
        images, K = check_clip(images, K)
        H, W = images.shape[1:3]
        x, Kt = resize_crop(images, K, self.target_hw(H, W), device=self.device)
        return BackboneInputs(images=x, K=Kt, src_hw=(H, W))

    def modules(self) -> list[torch.nn.Module]:
        return [self.net]

    def check_condition(self, condition: Condition | None,
                        inputs: BackboneInputs) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """Validate ``condition`` against the capabilities and the n frames of ``inputs``.

        Returns (None, None) without a condition, else float32 tensors on ``device``: T_wc [n,4,4] camera-to-world
        re-anchored at frame 0 (metres) and K [n,3,3] (pixels, model resolution): ``condition.K`` where given,
        else the calibrated ``inputs.K`` (Pi3X needs rays and DA3 intrinsics whenever they get poses)."""
        if condition is None:
            return None, None
        if CAP_COND_POSE not in self.capabilities:
            raise ModeNotSupported(f"backbone {self.name!r} does not accept pose conditioning")
        if condition.K is not None and CAP_COND_INTRINSICS not in self.capabilities:
            raise ModeNotSupported(f"backbone {self.name!r} does not accept intrinsics conditioning")
        n = inputs.images.shape[0]
        T = np.asarray(condition.T_wc, dtype=np.float64)
        if T.shape != (n, 4, 4) or not np.all(np.isfinite(T)):
            raise DataError(f"condition T_wc must be finite [{n},4,4], got {T.shape}")
        T_wc = torch.as_tensor(so3.relative_to_first(T), dtype=torch.float32, device=self.device)
        if condition.K is None:
            return T_wc, inputs.K.to(device=self.device, dtype=torch.float32)
        K = np.asarray(condition.K, dtype=np.float64)
        if K.shape != (n, 3, 3) or not np.all(np.isfinite(K)):
            raise CalibrationError(f"condition K must be finite [{n},3,3], got {K.shape}")
        return T_wc, torch.as_tensor(K, dtype=torch.float32, device=self.device)
