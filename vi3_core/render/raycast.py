"""Vectorised ray casting of a box world through a calibrated, distorted camera.

Rays are built once per camera: one per raw (distorted) pixel centre, through the exact inverse of the
distortion model, and one per pixel centre of the undistorted pinhole image (``calib.undistorter().K``). Ray
directions have camera z = 1, so the ray parameter at the first hit *is* the z-depth. The image is Lambertian
(texture x a per-face shade), so every view of a surface point has the same grey level: warping with exact
depth and poses reproduces it up to interpolation.

Arrays are kept per axis and per pixel ([3,H,W], structure of arrays) so that every operation runs on
contiguous vectors, and each box is tested only on the pixel rectangle its projection can cover.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

from vi3_core.render.scene import Scene

_EDGE_SAMPLES = np.linspace(0.0, 1.0, 17)


class _RaySet:
    """Rays [3,H,W] (camera frame, z = 1) of one pixel grid, and the map from normalised points to its pixels."""

    def __init__(self, rays: np.ndarray, to_pixels: Callable[[np.ndarray], np.ndarray]) -> None:
        self.rays = rays
        self.to_pixels = to_pixels


class CameraModel(Protocol):
    """What the renderer needs of a calibrated camera (``vi3_core.dataset.calib.CameraCalib`` is one): size (w, h)
    px, the undistorted pinhole camera (``undistorter().K`` [3,3]), and the maps between raw pixels [N,2] and
    normalised undistorted points [N,2]."""

    size: tuple[int, int]

    def undistorter(self): ...

    def distort(self, xy: np.ndarray) -> np.ndarray: ...

    def undistort_points(self, uv: np.ndarray) -> np.ndarray: ...


class Renderer:
    """Renders ``scene`` with ``calib``: raw mono8 images and exact z-depth of the undistorted image."""

    def __init__(self, scene: Scene, calib: CameraModel) -> None:
        self.scene = scene
        self.calib = calib
        w, h = calib.size
        self.shape = (h, w)
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        uv = np.stack([u.reshape(-1), v.reshape(-1)], 1)
        K = calib.undistorter().K

        def rays(xy: np.ndarray) -> np.ndarray:
            return np.concatenate([xy, np.ones((len(xy), 1))], 1).T.reshape(3, h, w).astype(np.float32)

        self.raw = _RaySet(rays(calib.undistort_points(uv)), calib.distort)
        self.undistorted = _RaySet(rays((uv - K[:2, 2]) / np.diag(K)[:2]), lambda xy: xy * np.diag(K)[:2] + K[:2, 2])

    def _box_window(self, rs: _RaySet, lo: np.ndarray, hi: np.ndarray, T_CW: np.ndarray
                    ) -> tuple[slice, slice] | None:
        """Pixel rectangle (rows, cols) that the box can cover; None when it is entirely behind the camera.

        The box's 8 corners give a rectangle in normalised coordinates; its boundary, mapped to pixels (the
        distortion is monotonic), bounds the box's image. Boxes straddling the camera plane get the full image.
        """
        h, w = self.shape
        corners = np.stack(np.meshgrid(*zip(lo, hi), indexing="ij"), -1).reshape(-1, 3)
        X = corners @ T_CW[:3, :3].T + T_CW[:3, 3]
        if np.all(X[:, 2] <= 0):
            return None
        if np.any(X[:, 2] <= 1e-3):
            return slice(0, h), slice(0, w)
        xy = X[:, :2] / X[:, 2:]
        (x0, y0), (x1, y1) = xy.min(0), xy.max(0)
        s = _EDGE_SAMPLES
        edge = np.concatenate([np.stack([x0 + (x1 - x0) * s, np.full_like(s, y)], 1) for y in (y0, y1)]
                              + [np.stack([np.full_like(s, x), y0 + (y1 - y0) * s], 1) for x in (x0, x1)])
        px = rs.to_pixels(edge)
        (u0, v0), (u1, v1) = np.floor(px.min(0)) - 2, np.ceil(px.max(0)) + 3
        rows = slice(int(np.clip(v0, 0, h)), int(np.clip(v1, 0, h)))
        cols = slice(int(np.clip(u0, 0, w)), int(np.clip(u1, 0, w)))
        return rows, cols

    def cast(self, T_WC: np.ndarray, rs: _RaySet) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """First hits of the rays of ``rs`` from camera pose T_WC [4,4], or one pose per image row [H,4,4] (a rolling
        shutter: each row exposed at its own time).

        Returns t [H,W] float32 (= z-depth for z = 1 rays; inf on a miss), face id [H,W] int64, and the world
        directions [3,H,W] float32.
        """
        sc = self.scene
        h, w = self.shape
        if T_WC.ndim == 3:
            d = np.einsum("rij,jrc->irc", T_WC[:, :3, :3].astype(np.float32), rs.rays)
            o = T_WC[:, :3, 3].T[:, :, None]  # [3,H,1]: each row's camera centre
        else:
            d = (T_WC[:3, :3].astype(np.float32) @ rs.rays.reshape(3, -1)).reshape(3, h, w)
            o = T_WC[:3, 3]
        with np.errstate(divide="ignore"):
            inv = 1.0 / d
        pos = d > 0
        # Inside the room: each axis exits through the wall it heads towards (the positive ray parameter).
        t_ax = [np.maximum(inv[a] * (sc.room_hi[a] - o[a]).astype(np.float32),
                           inv[a] * (sc.room_lo[a] - o[a]).astype(np.float32)) for a in range(3)]
        t = np.minimum(np.minimum(t_ax[0], t_ax[1]), t_ax[2])
        ax = np.where(t == t_ax[0], 0, np.where(t == t_ax[1], 1, 2))
        face = 2 * ax + np.take_along_axis(pos, ax[None], 0)[0]
        # a rolling shutter's rows see a box within the union of what its first, middle and last rows see
        poses = T_WC[[0, h // 2, h - 1]] if T_WC.ndim == 3 else T_WC[None]
        T_CWs = np.linalg.inv(poses)
        with np.errstate(invalid="ignore"):  # 0 * inf on rays parallel to a face: NaN, never a hit
            for b in range(len(sc.box_lo)):  # few boxes; each test is vectorised over its pixel window
                windows = [wdw for wdw in (self._box_window(rs, sc.box_lo[b], sc.box_hi[b], T) for T in T_CWs)
                           if wdw is not None]
                if not windows:
                    continue
                rows = slice(min(r.start for r, _ in windows), max(r.stop for r, _ in windows))
                cols = slice(min(c.start for _, c in windows), max(c.stop for _, c in windows))
                o_rows = o[:, rows] if np.ndim(o) == 3 else o
                near = far = axis_in = None
                for a in range(3):
                    inv_a = inv[a, rows, cols]
                    t1 = inv_a * (sc.box_lo[b, a] - o_rows[a]).astype(np.float32)
                    t2 = inv_a * (sc.box_hi[b, a] - o_rows[a]).astype(np.float32)
                    n_a, f_a = np.minimum(t1, t2), np.maximum(t1, t2)
                    if near is None:
                        near, far, axis_in = n_a, f_a, np.zeros(n_a.shape, np.int64)
                    else:
                        axis_in[n_a > near] = a
                        near, far = np.maximum(near, n_a), np.minimum(far, f_a)
                t_win, face_win = t[rows, cols], face[rows, cols]  # views: written in place
                hit = (near <= far) & (near > 0) & (near < t_win)
                t_win[hit] = near[hit]
                a = axis_in[hit]
                r_hit, c_hit = np.nonzero(hit)
                face_win[hit] = 6 + 6 * b + 2 * a + ~pos[:, rows, cols][a, r_hit, c_hit]
        return t, face, d

    def shade(self, T_WC: np.ndarray, t: np.ndarray, face: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Grey level [H,W] float32 in [0, 255] at the hits (bilinear texture lookup x face shade)."""
        sc = self.scene
        o = T_WC[:, :3, 3].T[:, :, None] if T_WC.ndim == 3 else T_WC[:3, 3, None, None]
        X = o.astype(np.float32) + t * d
        axis = sc.face_axis[face]
        # In-plane coordinates: (y, z) on x-faces, (x, z) on y-faces, (x, y) on z-faces.
        u = np.where(axis == 0, X[1], X[0])
        v = np.where(axis == 2, X[1], X[2])
        tu = (u - sc.face_origin[face, 0]) / sc.texel - 0.5
        tv = (v - sc.face_origin[face, 1]) / sc.texel - 0.5
        tw, th = sc.tex_w[face], sc.tex_h[face]
        x0 = np.clip(np.floor(tu), 0, tw - 2).astype(np.int64)
        y0 = np.clip(np.floor(tv), 0, th - 2).astype(np.int64)
        fx = np.clip(tu - x0, 0.0, 1.0)
        fy = np.clip(tv - y0, 0.0, 1.0)
        base = sc.tex_offset[face] + y0 * tw + x0
        a = sc.atlas
        top = a[base] * (1 - fx) + a[base + 1] * fx
        bot = a[base + tw] * (1 - fx) + a[base + tw + 1] * fx
        return (top * (1 - fy) + bot * fy) * sc.shade[face]

    def radiance(self, T_WC: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The raw (distorted) image's grey levels [H,W] float32 (0-255) from camera pose T_WC [4,4], or one pose per
        row [H,4,4], and the hits' ray parameter (z-depth of the raw rays) [H,W] float32 (inf on a miss)."""
        t, face, d = self.cast(T_WC, self.raw)
        return self.shade(T_WC, t, face, d), t

    def render(self, T_WC: np.ndarray, *, with_depth: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """Raw (distorted) mono8 image [H,W] uint8 and z-depth [H,W] float32 (m) of the undistorted image."""
        t, face, d = self.cast(T_WC, self.raw)
        image = np.clip(self.shade(T_WC, t, face, d) + 0.5, 0, 255).astype(np.uint8)
        depth = None
        if with_depth:
            depth = self.cast(T_WC, self.undistorted)[0]
            depth[~np.isfinite(depth)] = np.nan
        return image, depth
