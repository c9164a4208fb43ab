"""Plane-sweep multi-view stereo with OpenCV and numpy: dense z-depth and a matching-cost confidence per frame.

For a reference frame, ``n_depths`` fronto-parallel planes are swept uniformly in inverse depth over its depth
range; each source image is warped onto every plane (the planes' homographies as explicit maps, all planes in one
``cv2.remap``) and compared with the reference by zero-mean normalised cross-correlation (ZNCC, approximated as
described in ``plane_sweep``) over a ``window`` x ``window`` box (``cv2.boxFilter`` over all planes at once, planes
as channels).
The per-plane score is the mean of the ``best_k`` best sources (robust to occlusion), the depth the winning plane
refined by a parabola through its neighbours, and the confidence the probability mass of a softmax over the scores
within one plane of the winner, times the winning score: flat or repetitive texture, occlusions and pixels no source
sees get a low confidence.

Reference frames are independent, so ``workers`` threads sweep them concurrently (OpenCV and numpy release the
interpreter lock inside their calls); each frame's result is the same bits whatever the number of workers and however
they share OpenCV's thread pool. Against the earlier torch sweep (``grid_sample`` and summed-area tables) this costs a
quarter of the CPU per frame: the warps and box filters are OpenCV's, not a chain of broadcast tensor operations.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np

#: The warp's interpolation; pixels whose bilinear footprint leaves the source image come out NaN (not seen).
_WARP = dict(interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))
#: cv2.remap refuses maps with a side of SHRT_MAX or more; a frame's planes are warped as one [h, w*planes] map.
_REMAP_MAX_SIDE = 32767
#: the most planes a sweep takes: cv2.boxFilter sums at most 128 channels, the planes of one array
MAX_DEPTHS = 128


def select_sources(n: int, *, n_sources: int) -> np.ndarray:
    """[n,k] source frames of each reference frame: the k = min(n_sources, n-1) nearest in clip order (earlier
    first on ties). Neighbours overlap most; on short clips they still give enough parallax, and on the
    generated EuRoC-like clips they beat the widest-baseline choice (fewer occlusions and out-of-view pixels)."""
    idx = np.arange(n)
    gap = np.abs(idx[:, None] - idx[None]).astype(np.float64)
    gap[idx, idx] = np.inf
    return np.argsort(gap, axis=1, kind="stable")[:, :min(n_sources, n - 1)]


def plane_sweep(gray: np.ndarray, K: np.ndarray, R_wc: np.ndarray, t_wc: np.ndarray, depth_range: np.ndarray, *,
                frames: np.ndarray | None = None, n_depths: int = 24, n_sources: int = 2, best_k: int = 2,
                window: int = 7, temperature: float = 0.05, min_var: float = 1e-4,
                workers: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Depth and confidence of the reference ``frames`` (indices; None: every frame), each against its nearest
    frames of the clip.

    gray [n,h,w] float images; K [3,3] at that resolution; R_wc [n,3,3], t_wc [n,3] camera-to-world (any scale);
    depth_range [n,2] (near, far) per frame in the poses' units; n_depths: 2 to ``MAX_DEPTHS`` planes; workers: threads
    sweeping reference frames concurrently. Returns depth [r,h,w] (> 0, same units) and conf [r,h,w] in [0, 1],
    float32, of the r reference frames.
    """
    gray = np.asarray(gray, np.float32)
    n, h, w = gray.shape
    K, R_wc, t_wc = (np.asarray(a, np.float64) for a in (K, R_wc, t_wc))
    depth_range = np.asarray(depth_range, np.float64)
    sources = select_sources(n, n_sources=n_sources)
    steps = np.linspace(0.0, 1.0, n_depths)
    area = float(window * window)

    def box(x: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Sums over ``window`` x ``window`` boxes of each channel of x [h,w,c], edges replicated (into ``out``, of
        x's shape, where given)."""
        return cv2.boxFilter(x, -1, (window, window), dst=out, normalize=False,
                             borderType=cv2.BORDER_REPLICATE).reshape(x.shape)

    # Each image normalised to zero mean, unit variance over its own windows before warping, so that the
    # normalised correlation of the warped source needs two box sums per plane instead of five.
    g = np.ascontiguousarray(gray.transpose(1, 2, 0))  # [h,w,n]: frames as channels
    mu = box(g) / area
    normed = (g - mu) / np.sqrt(np.maximum(box(g * g) / area - mu * mu, 0.0) + min_var)
    energy = box(normed * normed)  # [h,w,n]
    frames_normed = [np.ascontiguousarray(normed[..., f]) for f in range(n)]
    K_inv = np.linalg.inv(K)
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)  # pixel rows and columns
    planes_per_remap = max(1, (_REMAP_MAX_SIDE - 1) // w)

    def sweep(i: int) -> tuple[np.ndarray, np.ndarray]:
        """Depth and confidence [h,w] of reference frame i; memory [h,w,k*D] a few times."""
        inv_near, inv_far = 1.0 / depth_range[i, 0], 1.0 / depth_range[i, 1]
        inv = inv_near + steps * (inv_far - inv_near)
        q = inv.astype(np.float32)
        src = sources[i]
        D = n_depths
        zncc = np.empty((len(src), h, w, D), np.float32)
        # buffers reused for every source: fresh [h,w,D] arrays cost their first writes' page faults each time
        wr, ww, sum_wr, den = (np.empty((h, w, D), np.float32) for _ in range(4))
        blocks = [slice(d0, min(d0 + planes_per_remap, D)) for d0 in range(0, D, planes_per_remap)]
        maps = {b.stop - b.start: [np.empty((h, w, b.stop - b.start), np.float32) for _ in range(3)] for b in blocks}
        warped = np.empty((h, w, D), np.float32)
        behind = np.empty((h, w, D), bool)
        unseen = np.empty((h, w, D), bool)
        ref = frames_normed[i][..., None]
        energy_i = np.ascontiguousarray(energy[..., i:i + 1])
        eps = np.float32(1e-6 * area * area)
        for s, j in enumerate(src):
            R_ji = R_wc[j].T @ R_wc[i]  # reference camera -> source camera
            t_ji = R_wc[j].T @ (t_wc[i] - t_wc[j])
            # Source pixel of reference pixel x = (u, v, 1) on the plane at inverse depth q: the homography
            # K R_ji K^-1 x + q K t_ji (K^-1's last row is (0, 0, 1)), as explicit maps [h,w,planes] warped by one
            # remap per block of planes (cv2.warpPerspective computed them in row blocks starting where its
            # thread's share began, so with concurrent sweeps a few pixels' depth moved from run to run).
            H0, Kt = (K @ R_ji @ K_inv).astype(np.float32), (K @ t_ji).astype(np.float32)
            rays = [(H0[r, 0] * u + H0[r, 1] * v + H0[r, 2])[..., None] for r in range(3)]  # [h,w,1] each
            qKt = q[:, None] * Kt  # [D,3]
            with np.errstate(divide="ignore", invalid="ignore"):  # z <= 0: see ``behind``
                for d in blocks:
                    zb, xb, yb = maps[d.stop - d.start]
                    np.add(rays[2], qKt[d, 2], out=zb)
                    np.less_equal(zb, 1e-6, out=behind[..., d])  # behind the source camera: a plane partly behind it
                    np.divide(np.add(rays[0], qKt[d, 0], out=xb), zb, out=xb)
                    np.divide(np.add(rays[1], qKt[d, 1], out=yb), zb, out=yb)
                    warped[..., d] = cv2.remap(frames_normed[j], xb.reshape(h, -1), yb.reshape(h, -1),
                                               **_WARP).reshape(h, w, -1)
            np.isnan(warped, out=unseen)  # [h,w,D]
            unseen |= behind
            np.copyto(warped, 0.0, where=unseen)
            # Dividing by the warped window's own energy keeps interpolation (which damps the warped texture at
            # fractional shifts) from biasing the disparity toward whole pixels.
            s_wr = box(np.multiply(warped, ref, out=wr), sum_wr)
            np.multiply(box(np.multiply(warped, warped, out=ww), den), energy_i, out=den)
            np.sqrt(np.add(den, eps, out=den), out=den)
            zs = np.divide(s_wr, den, out=zncc[s])  # in [-1, 1]
            np.copyto(zs, -2.0, where=unseen)
        # Mean of the best_k best sources that see the point (a surface seen by one source only keeps its score);
        # -1 where no source sees it.
        if best_k < len(src):
            zncc = -np.partition(-zncc, best_k - 1, axis=0)[:best_k]
        seen = zncc > -1.5
        count = seen.sum(0, dtype=np.float32)
        np.copyto(zncc, 0.0, where=~seen)
        score = zncc.sum(0)
        score /= np.maximum(count, 1.0)
        score -= count == 0  # [h,w,D]
        best = score.argmax(-1)[..., None]  # the first plane on ties
        lo, hi = np.maximum(best - 1, 0), np.minimum(best + 1, D - 1)
        s0, s1, s2 = (np.take_along_axis(score, k, -1) for k in (lo, best, hi))
        curv = s0 - 2 * s1 + s2
        fit = (curv < -1e-6) & (lo < best) & (hi > best)
        offset = np.divide(0.5 * (s0 - s2), curv, out=np.zeros_like(curv), where=fit)
        inv_best = inv_near + (best + np.clip(offset, -0.5, 0.5)) / (D - 1) * (inv_far - inv_near)
        prob = score  # softmax over the planes, shifted by its maximum, the winner's
        prob *= 1.0 / temperature
        prob -= s1 * (1.0 / temperature)
        np.exp(prob, out=prob)
        total = prob.sum(-1, keepdims=True)
        peak = (np.take_along_axis(prob, lo, -1) / total) * (lo < best) + np.take_along_axis(prob, best, -1) / total \
            + (np.take_along_axis(prob, hi, -1) / total) * (hi > best)
        return (1.0 / inv_best[..., 0]).astype(np.float32), (peak * np.maximum(s1, 0.0))[..., 0].astype(np.float32)

    refs = range(n) if frames is None else [int(i) for i in frames]
    if workers > 1 and len(refs) > 1:
        with ThreadPoolExecutor(max_workers=min(workers, len(refs)), thread_name_prefix="vi3-mvs") as pool:
            results = list(pool.map(sweep, refs))
    else:
        results = [sweep(i) for i in refs]
    return np.stack([d for d, _ in results]), np.stack([c for _, c in results])
