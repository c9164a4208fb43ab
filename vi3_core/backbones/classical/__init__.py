"""The embedded ``classical`` backbone: up-to-scale multi-view geometry from classical vision, CPU, no weights.

``preprocess`` does the non-differentiable work once per clip: the feature tracks of its frames, each frame tracked
once by a front end that lives across clips (``tracks.FrameTracker``: a clip that starts with the last frame of the
one before, as ``bind`` tells by the clip's stamps, continues its tracks; any other starts them afresh), structure
from motion into one consistent up-to-scale frame (``poses``, ``bundle``), held to the scale of a small map of
keyframes that lives across clips where they see the clip's points (``keyframes``; the prediction's ``units_link``
then says how its units moved from the clip before), and plane-sweep stereo at the working resolution (``mvs``) of the
frames whose depth is read (``bind``'s ``depth_frames``; the others NaN with zero confidence).
``forward`` then applies explicit trainable corrections, zero at the start, so that the base forward is exactly the
classical result and test-time refinement can move poses and depth:

- camera_head: per-frame rotation-vector and translation offsets of frames 1..n-1 (frame 0 stays the world);
  R_wc = exp(dw) R_wc_base, t_wc = t_wc_base + dt;
- depth_head: a log-depth offset per working-resolution pixel, depth = depth_base * exp(dlog);
- global_blocks: none.

Scale is normalised the way VGGT normalises its training targets: the confidence-weighted mean distance of the
dense points of the frames with depth from the first camera centre is 1 (``metric`` is False).

Frames whose long side exceeds ``max_side`` (1024 px) are first shrunk to it (area averaging): the tracker's
windows, corner spacing and pyramid are sized for frames of EuRoC's size (752x480), and at 4512x2880 its tracks
failed (every clip a "backbone failure") while the plane sweep at a quarter of the frame took 3 GB.

A clip the geometry cannot be recovered from (too few tracks, no image motion, rotation only) is not an error:
the inputs carry ``status`` (``ok`` | ``few_features`` | ``stationary`` | ``no_parallax``) and a ``reason``,
the confidence is zero everywhere, depth is a constant 1, translations are zero and rotations are those of a
pure-rotation fit of the tracks where one was made (``no_parallax``, a failed registration), else the identity.
The last clip's inputs, status and reason are also on the backbone (``last_inputs``, ``last_status``,
``last_reason``, and with the SfM counts and stage timings ``diagnostics()``) for callers of ``predict``.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field

import cv2
import numpy as np
import torch

from vi3_core import so3, so3_torch
from vi3_core.backbones._hub import check_clip, scaled_K
from vi3_core.backbones.base import (
    CAP_TTR,
    Backbone,
    BackboneInputs,
    Condition,
    GyroRotations,
    ParamGroups,
    Prediction,
)
from vi3_core.backbones.classical.keyframes import KeyframeMap
from vi3_core.backbones.classical.mvs import MAX_DEPTHS, plane_sweep
from vi3_core.backbones.classical.poses import SfmResult, estimate_poses, project
from vi3_core.backbones.classical.tracks import FrameTracker, TrackerOptions, Tracks
from vi3_core.backbones.front_end import FrameLosses
from vi3_core.camera import backproject
from vi3_core.errors import DataError, ModeNotSupported
from vi3_core.threads import torch_threads
from vi3_core.types import UnitsLink

# a clip whose formal sigma of its trajectory against its depth cannot be computed (a frame no point constrains, too
# few observations): its trajectory is taken as unknown against its depth (100 %), its depth still links the chain
UNKNOWN_TRAJ_DEPTH_SIGMA = 1.0


class Corrections(torch.nn.Module):
    """Trainable corrections of one clip, all zero at creation.

    rotvec [n-1,3] rad and trans [n-1,3] (model units) for frames 1..n-1; log_depth [n,h,w].
    """

    def __init__(self, n: int, hw: tuple[int, int], *, device: torch.device, dtype: torch.dtype) -> None:
        super().__init__()
        self.rotvec = torch.nn.Parameter(torch.zeros(n - 1, 3, device=device, dtype=dtype))
        self.trans = torch.nn.Parameter(torch.zeros(n - 1, 3, device=device, dtype=dtype))
        self.log_depth = torch.nn.Parameter(torch.zeros(n, *hw, device=device, dtype=dtype))


@dataclass
class ClassicalInputs(BackboneInputs):
    """``BackboneInputs`` plus the clip's classical result and its corrections.

    base_R_wc [n,3,3], base_t_wc [n,3] camera-to-world (frame 0 = identity, normalised scale); base_depth,
    base_conf [n,h,w]; corrections: this clip's ``Corrections``; status/reason: see the module docstring;
    diagnostics: counts, errors, stage timings (s), the plane-sweep threads (mvs_workers) and the front end's losses
    (front_end, ``ClassicalBackbone.diagnostics``); units_link: its normalised units against the clip before's, where
    the keyframes held its scale (``UnitsLink``).
    """

    base_R_wc: torch.Tensor
    base_t_wc: torch.Tensor
    base_depth: torch.Tensor
    base_conf: torch.Tensor
    corrections: Corrections
    status: str
    reason: str
    diagnostics: dict = field(default_factory=dict)
    units_link: UnitsLink | None = None


def _area_resized(images: np.ndarray, K: np.ndarray, hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``images`` [n,H,W(,3)] resized (area averaging, same dtype) to ``hw`` = (h, w) and the new grid's K [3,3]
    (pixels)."""
    H, W = images.shape[1:3]
    h, w = hw
    if (h, w) == (H, W):
        return images, K
    small = np.stack([cv2.resize(im, (w, h), interpolation=cv2.INTER_AREA) for im in images])
    return small, scaled_K(K, w / W, h / H)


def _shrunk(images: np.ndarray, K: np.ndarray, max_side: int) -> tuple[np.ndarray, np.ndarray]:
    """``images`` [n,H,W(,3)] uint8 and their K [3,3] (pixels), shrunk uniformly so that the long side is
    ``max_side`` when it is longer; else unchanged."""
    H, W = images.shape[1:3]
    s = min(max_side / max(H, W), 1.0)
    return _area_resized(images, K, (max(int(round(H * s)), 1), max(int(round(W * s)), 1)))


def _depth_range(sfm: SfmResult, visible: np.ndarray, K: np.ndarray, *, margin: float) -> tuple[float, float]:
    """(near, far) of the plane sweep: the 1st and 99th percentiles of the z-depths of the sparse points in the
    views that see them (``visible`` [m,n]; ``K`` [3,3] of the tracked images), widened by ``margin``. One range
    for the whole clip, and a wide one, because a surface with few tracks (a box that just came into view) must
    still fall inside it; sampling in inverse depth keeps a wide range affordable."""
    _, z = project(sfm.points, sfm.R_wc, sfm.t_wc, K)
    z = z[visible & np.isfinite(z) & (z > 0)]
    return float(np.percentile(z, 1)) / margin, float(np.percentile(z, 99)) * margin


def _kept_scale(sfm: SfmResult) -> bool:
    """Whether the clip's structure from motion is at the scale of the clip before: the points it carried started
    it (``warm_start``) or the keyframes held it (``anchored``)."""
    return bool(sfm.diagnostics.get("warm_start") or sfm.diagnostics.get("anchored"))


class ClassicalBackbone(Backbone):
    """Classical multi-view geometry behind the backbone contract (see the module docstring).

    Options (keyword-only): ``max_side`` px, the longest side a frame is worked on at (larger ones are shrunk
    first); ``downscale`` input pixels per working pixel (4: 752x480 -> 188x120); ``tracker``: the front end's
    ``TrackerOptions`` (its ``max_features`` tracked corners per frame); ``n_depths``, ``n_sources``, ``best_k``,
    ``window``: plane-sweep settings (see ``mvs.plane_sweep``); ``bundle_adjust``: refine poses and points jointly;
    ``gyro_sigma_deg``: the 1-sigma of the gyro's rotation of each frame (its noise, and what is left of the mount's
    and the time offset's errors) when ``bind`` gives the clip's (``GyroRotations``): the bundle adjustment's prior on
    the rotations, up to a gyro bias the clip fits (0: no prior, the images alone); ``traj_depth_inflation``: the
    factor on the bundle adjustment's formal 1-sigma of the trajectory's scale against the depth's
    (``bundle.Adjusted``) that the prediction reports as its ``traj_depth_sigma`` (0: none). The formal one takes
    the tracks' pixel errors as independent (and is right for such errors); the tracker's are not, and on two renders
    with depth ground truth (the V1_02-like and a handheld RealSense-like one, 77 clips) the clips' log(trajectory
    scale / depth scale) came out at 3.75 formal sigmas (robust 1-sigma of the ratio; 3.1 and 4.4 apart);
    ``keyframes``: hold each clip's bundle adjustment to the keyframes of the clips before (``keyframes.KeyframeMap``;
    False: each clip's scale is what its own frames hand on); ``held_scale_inflation``: the factor on the adjustment's
    formal 1-sigma of the clip's scale against the held keyframes that the prediction's ``units_link`` reports (the
    chained scale's change per link on the real recording and three handheld renders came out at 1.4-4.4 times it);
    ``threads``: Python threads that sweep reference frames concurrently (None: torch's intra-op thread count when
    the clip comes, the process's ``threads`` setting, see ``vi3_core.threads``).

    ``preprocess`` holds torch's intra-op pool at one thread: its OpenMP workers meet at a barrier after every
    operator, and when another process (or the node's executor) takes a core, the waiting worker spins; on the
    shared 2-core machine that made the plane sweep ~7x slower. Independent reference frames on
    separate threads use both cores without a barrier per operator.
    """

    name = "classical"
    metric = False
    capabilities = frozenset({CAP_TTR})
    patch_size = 1  # no patch grid: the working resolution is the input divided by ``downscale``
    # The trainable groups are explicit corrections in radians, model units and log-depth, not network weights.
    # Adam's first steps move every coordinate by about lr: 1e-4 rad (0.006 deg) is below this backbone's pose
    # error, whereas 1e-3 overshot it and made the TTR loss rise for the first ~20 steps.
    ttr_lr = 1e-4

    def __init__(self, *, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32,
                 max_side: int = 1024, downscale: float = 4.0, tracker: TrackerOptions | None = None,
                 n_depths: int = 24,
                 n_sources: int = 2, best_k: int = 2, window: int = 7, bundle_adjust: bool = True,
                 gyro_sigma_deg: float = 0.05, traj_depth_inflation: float = 3.75, keyframes: bool = True,
                 held_scale_inflation: float = 3.75, threads: int | None = None) -> None:
        super().__init__(device=device, dtype=dtype)
        if downscale < 1 or max_side < 64:
            raise ValueError(f"downscale must be >= 1 and max_side >= 64, got {downscale} and {max_side}")
        if not 2 <= n_depths <= MAX_DEPTHS:
            raise ValueError(f"n_depths must be within 2..{MAX_DEPTHS}, got {n_depths}")
        self.max_side = max_side
        self.downscale = downscale
        self.tracker = FrameTracker(tracker)
        self.keyframes = KeyframeMap() if keyframes else None
        if not (math.isfinite(held_scale_inflation) and held_scale_inflation > 0):
            raise ValueError(f"held_scale_inflation must be finite and > 0, got {held_scale_inflation}")
        self.held_scale_inflation = held_scale_inflation
        # the last clip whose scale the keyframe map held or carried: (its first key, its last key, its scale divisor)
        self._units: tuple[float, float, float] | None = None
        if threads is not None and threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        if not (math.isfinite(gyro_sigma_deg) and gyro_sigma_deg >= 0):
            raise ValueError(f"gyro_sigma_deg must be finite and >= 0, got {gyro_sigma_deg}")
        self.gyro_sigma = math.radians(gyro_sigma_deg)
        if not (math.isfinite(traj_depth_inflation) and traj_depth_inflation >= 0):
            raise ValueError(f"traj_depth_inflation must be finite and >= 0, got {traj_depth_inflation}")
        self.traj_depth_inflation = traj_depth_inflation
        self.threads = threads
        self.mvs_options = dict(n_depths=n_depths, n_sources=n_sources, best_k=best_k, window=window)
        self.bundle_adjust = bundle_adjust
        #: The last clip's inputs (status, reason, diagnostics); its corrections are what ``param_groups`` returns.
        self.last_inputs: ClassicalInputs | None = None
        self._depth_frames: np.ndarray | None = None  # of the clip bound, for its ``preprocess``
        self._stamps: np.ndarray | None = None  # of the clip bound: the keys of its frames in the tracker
        self._gyro: GyroRotations | None = None  # of the clip bound
        # the last clip's structure for the next one's warm start: (its last frame's key, track ids [m], points [m,3]
        # in that last camera's frame, at that clip's SfM scale)
        self._structure: tuple[float, np.ndarray, np.ndarray] | None = None

    def bind(self, clip, *, depth_frames: np.ndarray | None = None, continued: bool = True,
             gyro: GyroRotations | None = None) -> None:
        """The clip the next ``preprocess`` sees: its frames' stamps (which of them the front end tracked already),
        the frames whose depth is read (the plane sweep runs for those only) and its rotations from the gyro (the
        bundle adjustment's prior); not ``continued``: tracked afresh."""
        self._depth_frames, self._gyro = depth_frames, gyro
        self._stamps = None if clip is None or not continued else np.asarray(clip.stamps, np.float64)

    def forget(self) -> None:
        """Drop the front end's tracks, the carried structure and the last clip's inputs (``Backbone.forget``)."""
        self.tracker.reset()
        if self.keyframes is not None:
            self.keyframes.reset()
        self._structure, self.last_inputs, self._units = None, None, None

    @property
    def last_status(self) -> str:
        """Status of the last preprocessed clip ('' before any)."""
        return "" if self.last_inputs is None else self.last_inputs.status

    @property
    def last_reason(self) -> str:
        """Reason of the last preprocessed clip's status ('' before any)."""
        return "" if self.last_inputs is None else self.last_inputs.reason

    def diagnostics(self) -> dict:
        """The last clip's status and reason, its SfM counts and errors (tracks, points, reproj_px_median, ...),
        the scale divisor, the stage timings tracks_s, sfm_s, mvs_s (s), mvs_workers (plane-sweep threads) and
        front_end: where the tracks into the frames this clip tracked were lost (``front_end.FrameLosses`` as a dict);
        empty before any clip."""
        if self.last_inputs is None:
            return {}
        return {"status": self.last_inputs.status, "reason": self.last_inputs.reason, **self.last_inputs.diagnostics}

    def working_size(self, H: int, W: int) -> tuple[int, int]:
        """(h, w) of the working resolution for (H, W) input images: each side divided by ``downscale`` and rounded
        (at least 8); ``preprocess`` resizes the images to it (area averaging; the sides' scales differ by the
        rounding)."""
        return max(int(round(H / self.downscale)), 8), max(int(round(W / self.downscale)), 8)

    def preprocess(self, images: np.ndarray, K: np.ndarray) -> ClassicalInputs:
        """images [n,H,W] or [n,H,W,3] uint8 (undistorted, RGB), K [3,3] -> ``ClassicalInputs`` on ``device``:
        images [n,3,h,w] (grey replicated, in [0,1]) and K [n,3,3] at the working resolution."""
        workers = self.threads or torch.get_num_threads()
        depth_frames, self._depth_frames = self._depth_frames, None
        stamps, self._stamps = self._stamps, None
        gyro, self._gyro = self._gyro, None
        with torch_threads(1):
            return self._preprocess(images, K, workers, depth_frames, stamps,
                                    gyro if gyro is not None and len(gyro.R_wc) == len(images) else None)

    def _track(self, gray: np.ndarray, stamps: np.ndarray | None) -> tuple[Tracks, list[float], FrameLosses]:
        """The tracks of the clip's frames ``gray`` [n,H,W], the frames' keys and what became of the tracks into the
        frames this clip added: the frames the front end has not seen are added in order (each frame once); a clip
        that does not continue the front end's last frame (or comes without stamps: ``predict`` without ``bind``)
        starts it afresh."""
        tr = self.tracker
        tr.hold(len(gray))
        if stamps is None or len(stamps) != len(gray):
            tr.reset()
            keys = [float(i) for i in range(len(gray))]
        else:
            keys = [float(t) for t in stamps]
        seen = set(tr.keys())
        done = 0
        while done < len(keys) and keys[done] in seen:  # the leading frames tracked already (the shared ones)
            done += 1
        continues = done > 0 and tr.frame_shape == gray.shape[1:] and \
            (done == len(keys) or tr.last_key == keys[done - 1])
        if not continues:
            tr.reset()
            if self.keyframes is not None:
                self.keyframes.reset()
            self._structure, done = None, 0
        for key, g in zip(keys[done:], gray[done:]):
            tr.add(key, g)
        return tr.tracks(keys), keys, tr.losses(keys[done:])

    def _known(self, tracks: Tracks, first_key: float) -> np.ndarray | None:
        """[m,3] points of ``tracks`` the clip before reconstructed, in this clip's world (its first camera, which was
        that clip's last), at that clip's SfM scale; None when the clip does not start where that one ended."""
        kept = self._structure
        if kept is None or kept[0] != first_key or not len(kept[1]):
            return None
        _, ids, points = kept
        idx = np.minimum(np.searchsorted(ids, tracks.ids), len(ids) - 1)
        return np.where((ids[idx] == tracks.ids)[:, None], points[idx], np.nan)

    def _keep_structure(self, sfm, tracks: Tracks, last_key: float) -> None:
        """The clip's points in its last camera's frame, for the next clip's warm start (none after a failure)."""
        if not sfm.ok:
            self._structure = None
            return
        R, t = sfm.R_wc[-1], sfm.t_wc[-1]
        good = np.isfinite(sfm.points[:, 0])
        self._structure = (last_key, tracks.ids[good], (sfm.points[good] - t) @ R)

    def _units_link(self, sfm: SfmResult, keys: list[float]) -> UnitsLink | None:
        """The clip's ``UnitsLink`` to the clip before: where the keyframes held its bundle adjustment, the ratio of
        the two clips' scale divisors (both in the map's units), of 1-sigma ``held_scale_inflation`` times the
        adjustment's formal one of the clip's scale against the keyframes' (``bundle.Adjusted.held_scale_sigma``);
        None elsewhere. Remembers the clip for the next."""
        prev, self._units = self._units, None
        if not sfm.ok or self.keyframes is None:
            return None
        s = float(sfm.diagnostics["scale_divisor"])
        if _kept_scale(sfm):
            self._units = (keys[0], keys[-1], s)
        formal = float(sfm.diagnostics.get("held_scale_sigma", float("nan")))
        if not sfm.diagnostics.get("anchored") or not math.isfinite(formal) or prev is None or prev[1] != keys[0]:
            return None
        return UnitsLink(prev[0], math.log(prev[2] / s), self.held_scale_inflation * formal)

    @staticmethod
    def _extend_map(kf: KeyframeMap, sfm: SfmResult, gray_last: np.ndarray, keys: list[float]) -> None:
        """The clip's end recorded in the keyframe map (``KeyframeMap.extend``; a failed clip resets it)."""
        if not sfm.ok:
            kf.reset()
            return
        good = np.isfinite(sfm.points[:, 0])
        depth = float(np.median(np.linalg.norm(sfm.points[good] - sfm.t_wc[-1], axis=1))) if good.any() else 0.0
        kf.extend(gray_last, keys[-1], keys[0], so3.make_T(sfm.R_wc[-1], sfm.t_wc[-1]), depth,
                  same_scale=_kept_scale(sfm))

    def _preprocess(self, images: np.ndarray, K: np.ndarray, workers: int, depth_frames: np.ndarray | None,
                    stamps: np.ndarray | None, gyro: GyroRotations | None) -> ClassicalInputs:
        images, K = check_clip(images, K)
        src_hw = images.shape[1:3]
        images, K = _shrunk(images, K, self.max_side)
        n, H, W = images.shape[:3]
        h, w = self.working_size(H, W)
        dev = self.device
        gray = images if images.ndim == 3 else np.stack([cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in images])
        # the working resolution, in float so that a faint texture keeps its sub-grey-level shading
        small, K_w = _area_resized(np.divide(gray, np.float32(255.0), dtype=np.float32), K, (h, w))
        img = torch.from_numpy(small).to(dev)[:, None].expand(n, 3, h, w)
        K_t = torch.as_tensor(K_w, dtype=torch.float32, device=dev).expand(n, 3, 3)

        timings = {}
        t0 = time.perf_counter()
        tracks, keys, losses = self._track(gray, stamps)
        timings["tracks_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        kf = self.keyframes
        anchor = None if kf is None else (lambda points: kf.anchors(gray, K, tracks, points, keys[0]))
        sfm = estimate_poses(tracks, K, known=self._known(tracks, keys[0]), bundle_adjust=self.bundle_adjust,
                             gyro=gyro, gyro_sigma=self.gyro_sigma, anchor=anchor)
        timings["sfm_s"] = time.perf_counter() - t0
        self._keep_structure(sfm, tracks, keys[-1])
        if kf is not None:
            t0 = time.perf_counter()
            self._extend_map(kf, sfm, gray[-1], keys)
            timings["keyframes_s"] = time.perf_counter() - t0

        t_wc = sfm.t_wc
        depth, conf = np.ones((n, h, w), np.float32), np.zeros((n, h, w), np.float32)
        if sfm.ok:
            t0 = time.perf_counter()
            near, far = _depth_range(sfm, tracks.visible, K, margin=2.0)
            swept = np.arange(n) if depth_frames is None else np.asarray(depth_frames, np.int64)
            d, c = plane_sweep(small, K_w, sfm.R_wc, sfm.t_wc, np.tile([near, far], (n, 1)),
                               frames=swept, workers=workers, **self.mvs_options)
            timings["mvs_s"] = time.perf_counter() - t0
            # Scale normalisation (VGGT-style): confidence-weighted mean distance of the dense points from the
            # first camera centre (the world origin) = 1; the sparse points' mean distance if nothing is confident.
            if float(c.sum()) > 1e-6:
                pts, _ = backproject(d, np.broadcast_to(K_w, (len(swept), 3, 3)),
                                     so3.make_T(sfm.R_wc[swept], sfm.t_wc[swept]))  # [r,h*w,3]
                s = float((c.reshape(len(swept), -1) * np.linalg.norm(pts, axis=-1)).sum() / c.sum())
            else:
                s = float(np.linalg.norm(sfm.points[np.isfinite(sfm.points[:, 0])], axis=1).mean())
            depth[:] = np.nan
            depth[swept], conf[swept] = d / s, c
            t_wc = t_wc / s
            sfm.diagnostics["scale_divisor"] = s
        units_link = self._units_link(sfm, keys)
        dt = self.dtype
        R, t, depth, conf = (torch.as_tensor(a, dtype=dt, device=dev) for a in (sfm.R_wc, t_wc, depth, conf))
        inputs = ClassicalInputs(
            images=img.to(dt), K=K_t.to(dt), src_hw=src_hw, base_R_wc=R, base_t_wc=t, base_depth=depth, base_conf=conf,
            corrections=Corrections(n, (h, w), device=dev, dtype=dt), status=sfm.status, reason=sfm.reason,
            diagnostics={**sfm.diagnostics, **timings, "mvs_workers": workers, "front_end": asdict(losses)},
            units_link=units_link)
        self.last_inputs = inputs
        return inputs

    def forward(self, inputs: BackboneInputs, condition: Condition | None = None) -> Prediction:
        """Base geometry of ``inputs`` with its corrections applied (differentiable in the corrections)."""
        if condition is not None:
            raise ModeNotSupported("the classical backbone takes no input conditioning (use init-only or TTR)")
        if not isinstance(inputs, ClassicalInputs):
            raise DataError(f"classical forward needs ClassicalInputs from its preprocess, got {type(inputs).__name__}")
        c = inputs.corrections
        R = torch.cat([inputs.base_R_wc[:1], so3_torch.exp(c.rotvec) @ inputs.base_R_wc[1:]])
        t = torch.cat([inputs.base_t_wc[:1], inputs.base_t_wc[1:] + c.trans])
        depth = inputs.base_depth * torch.exp(c.log_depth)
        formal = float(inputs.diagnostics.get("traj_depth_sigma", 0.0))
        if not self.traj_depth_inflation:
            tds = 0.0
        elif math.isfinite(formal):
            tds = self.traj_depth_inflation * formal
        else:
            tds = UNKNOWN_TRAJ_DEPTH_SIGMA
        return Prediction(R_wc=R, t_wc=t, K=inputs.K, depth=depth, conf=inputs.base_conf, metric=False,
                          traj_depth_sigma=tds, units_link=inputs.units_link)

    def param_groups(self) -> ParamGroups:
        """camera_head: [rotvec, trans]; depth_head: [log_depth] of the last preprocessed clip (empty before)."""
        if self.last_inputs is None:
            return ParamGroups()
        c = self.last_inputs.corrections
        return ParamGroups(camera_head=[c.rotvec, c.trans], depth_head=[c.log_depth], global_blocks=[])

    def modules(self) -> list[torch.nn.Module]:
        return [] if self.last_inputs is None else [self.last_inputs.corrections]
