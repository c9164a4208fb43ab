"""A rolling-shutter camera's frames as a global-shutter camera would have taken them, from the gyro (beyond the
paper, which assumes a global shutter).

A rolling shutter exposes the rows one after the other over the readout time; the frame's stamp is its middle row's
time (``row_times``). While the camera turns at angular rate w, a row read tau after the stamp sees the scene turned
by w tau: at 1 rad/s and a 25 ms readout the top and bottom rows of a 906 px camera are 23 px apart from where a
global shutter puts them, and the frame's geometry (its rotation against the gyro, the depth across its rows) is
bent. ``derolled`` moves every pixel back to the stamp's camera, to first order in the rotation during the readout
(the rate constant over the frame, the source row's time taken as the target row's), as VIO systems correct such
cameras; the translation during the readout (at walking speed millimetres) is left, as it needs the depth.
"""

from __future__ import annotations

import cv2
import numpy as np

MAP_STEP_PX = 8  # px: the pixel map is computed on a grid this coarse and interpolated (it is nearly linear)


def row_times(stamp_s: float, height: int, readout_s: float, rows: np.ndarray | None = None) -> np.ndarray:
    """[R] s: when the rows ``rows`` [R] (pixel rows, fractional where between rows; None: every row, R = height) of
    the frame stamped ``stamp_s`` (its middle row) were exposed (mid-exposure)."""
    rows = np.arange(height) if rows is None else rows
    return stamp_s + readout_s * ((rows + 0.5) / height - 0.5)


def derolled(images: np.ndarray, K: np.ndarray, rates_c: np.ndarray, readout_s: float, *,
             interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    """``images`` [n,H,W] or [n,H,W,3] (uint8 frames, or float32 maps such as depth) of a pinhole camera ``K`` [3,3]
    (undistorted) with rows read top first over ``readout_s`` s, turning at ``rates_c`` [n,3] rad/s (camera frame)
    during each frame -> the frames [same shape] as seen from the camera at each frame's stamp. A point at bearing b
    from that camera was recorded by the row read tau later at b - tau (w x b); each output pixel takes its value from
    there (``interpolation``: cv2's, bilinear by default, nearest for depth; pixels whose source is outside the frame
    repeat the border)."""
    n, H, W = images.shape[:3]
    if np.shape(rates_c) != (n, 3):
        raise ValueError(f"derolled: rates_c must be [{n},3] (one rate per frame), got {list(np.shape(rates_c))}")
    if readout_s == 0.0:
        return images
    # The map is computed on a grid of MAP_STEP_PX cells reaching a cell beyond every border and resized (bilinear)
    # to the pixels: with cv2.resize's sample positions the grid's point j sits at pixel j s + (s - 1) / 2 - s, so
    # that the resized map is exact where the map is linear, and no pixel lies beyond the outermost points.
    s = MAP_STEP_PX
    hc, wc = -(-H // s) + 2, -(-W // s) + 2
    u = np.arange(wc) * s + (s - 1) / 2 - s
    v = np.arange(hc) * s + (s - 1) / 2 - s
    x = ((u - K[0, 2]) / K[0, 0])[None, :]
    y = ((v - K[1, 2]) / K[1, 1])[:, None]
    tau = row_times(0.0, H, readout_s, v)[:, None]
    out = np.empty_like(images)
    for i, (wx, wy, wz) in enumerate(np.asarray(rates_c, np.float64)):
        zs = 1.0 - tau * (wx * y - wy * x)
        maps = [(f * (a - tau * b) / zs + c).astype(np.float32) for f, a, b, c in
                ((K[0, 0], x, wy - wz * y, K[0, 2]), (K[1, 1], y, wz * x - wx, K[1, 2]))]
        map_x, map_y = (np.ascontiguousarray(cv2.resize(m, (wc * s, hc * s), interpolation=cv2.INTER_LINEAR)
                                             [s:s + H, s:s + W]) for m in maps)
        out[i] = cv2.remap(images[i], map_x, map_y, interpolation, borderMode=cv2.BORDER_REPLICATE)
    return out


__all__ = ["MAP_STEP_PX", "derolled", "row_times"]
