"""Top-down trajectory and point-cloud figure (matplotlib, Agg canvas; no display needed).

Colours follow the paper's figures: GT black, base 3DFM red, IMU (metric inertial target) blue, VI3 green.
"Top-down" is the plane orthogonal to gravity: each clip is drawn in its first camera frame C1 rotated so that
the vertical axis is the GT gravity direction (``ClipEval.down_c1``) and the horizontal x axis is the first
camera's viewing direction projected onto the ground plane. A companion figure (``save_sigma_plot``) shows the
claimed clips' scale errors against their scale sigmas.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PathCollection
from matplotlib.figure import Figure

from vi3_core import so3
from vi3_core.camera import backproject as backproject_depth
from vi3_core.eval.claims import NO_SIGMA, Claims
from vi3_core.eval.clip_eval import ClipEval
from vi3_core.types import Geometry

COLORS: dict[str, str] = {"gt": "black", "base": "tab:red", "imu": "tab:blue", "init": "tab:cyan",
                          "vi3": "tab:green"}
#: GT thick; the IMU target dashed and wide, so that it stays visible under a VI3 trajectory that matches it.
LINE_STYLES: dict[str, dict] = {"gt": {"lw": 2.5}, "imu": {"lw": 3.0, "ls": "--"}}
LABELS: dict[str, str] = {"gt": "GT", "base": "Base 3DFM", "imu": "IMU", "init": "VI3 (fast init)", "vi3": "VI3"}


def ground_basis(down: np.ndarray) -> np.ndarray:
    """[2,3] rows: the ground-plane axes (forward = camera z projected, left) for gravity direction ``down`` [3]
    given in the camera frame."""
    up = -np.asarray(down, dtype=np.float64) / np.linalg.norm(down)
    fwd = np.array([0.0, 0.0, 1.0]) - up[2] * up
    if np.linalg.norm(fwd) < 1e-6:  # camera looking straight up/down: use its x axis instead
        fwd = np.array([1.0, 0.0, 0.0]) - up[0] * up
    fwd /= np.linalg.norm(fwd)
    return np.stack([fwd, np.cross(up, fwd)])


def backproject(geometry: Geometry, *, step: int = 8, max_points: int = 20000, seed: int = 0) -> np.ndarray:
    """World points [N,3] (first camera frame) of every ``step``-th pixel with valid depth, at most
    ``max_points`` (a deterministic random subset)."""
    pts, depth = backproject_depth(geometry.depth, geometry.K, so3.relative_to_first(geometry.T_wc), stride=step)
    pts, depth = pts.reshape(-1, 3), depth.reshape(-1)
    with np.errstate(invalid="ignore"):
        pts = pts[np.isfinite(pts).all(axis=1) & (depth > 0)]
    if len(pts) > max_points:
        pts = pts[np.sort(np.random.default_rng(seed).choice(len(pts), max_points, replace=False))]
    return pts


def draw_clip(ax_traj, ax_cloud, e: ClipEval) -> None:
    """Draw clip ``e`` on two matplotlib axes: top-down trajectories and top-down point cloud."""
    B = ground_basis(e.down_c1)
    for name, T in e.trajectories().items():
        xy = so3.relative_to_first(T)[:, :3, 3] @ B.T
        ax_traj.plot(xy[:, 0], xy[:, 1], marker="o", ms=3, color=COLORS[name], label=LABELS[name],
                     **LINE_STYLES.get(name, {"lw": 1.5}))
    clouds = ([("base", e.result.base)] if e.result is not None else []) + ([("vi3", e.vi3_geometry())] if e.ok else [])
    for name, geometry in clouds:
        xy = backproject(geometry) @ B.T
        ax_cloud.scatter(xy[:, 0], xy[:, 1], s=1.0, color=COLORS[name], alpha=0.5, lw=0, label=f"{LABELS[name]} points")
    gt_xy = e.T_gt[:, :3, 3] @ B.T
    ax_cloud.plot(gt_xy[:, 0], gt_xy[:, 1], "-o", ms=3, color=COLORS["gt"], label="GT cameras")
    frames = f"frames {int(e.indices[0])}-{int(e.indices[-1])}"
    ax_traj.set_title(f"{frames}: trajectories (top-down), init {e.status}", fontsize=9)
    ax_cloud.set_title(f"{frames}: point cloud (top-down)", fontsize=9)
    for ax in (ax_traj, ax_cloud):
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("forward (m)")
        ax.set_ylabel("left (m)")
        ax.grid(alpha=0.3)
        legend = ax.legend(fontsize=7, loc="best")
        for handle in legend.legend_handles:  # the cloud's tiny points, legible in the legend
            if isinstance(handle, PathCollection):
                handle.set_sizes([20.0])
                handle.set_alpha(1.0)


def save_plot(path: str | Path, evals: Sequence[ClipEval], *, max_clips: int = 3, title: str = "") -> Path:
    """Write a PNG with one row per clip (at most ``max_clips``, spread over the sequence): top-down
    trajectories (GT black, base red, IMU blue, VI3 green) and the top-down point cloud (base red, VI3 green)."""
    if not evals:
        raise ValueError(f"save_plot({path}): no evaluated clips to plot")
    pick = np.unique(np.linspace(0, len(evals) - 1, min(max_clips, len(evals))).round().astype(int))
    fig = Figure(figsize=(12, 4.8 * len(pick)), dpi=100)
    FigureCanvasAgg(fig)
    axes = fig.subplots(len(pick), 2, squeeze=False)
    for row, k in enumerate(pick):
        draw_clip(axes[row, 0], axes[row, 1], evals[k])
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png")
    return path


def sigma_plot_path(png: str | Path) -> Path:
    """The sigma plot that accompanies the plot ``png``: ``<stem>_sigma.png`` beside it."""
    png = Path(png)
    return png.with_name(f"{png.stem}_sigma{png.suffix or '.png'}")


def draw_sigma(ax, series: dict[str, Claims]) -> None:
    """Draw each claimed clip's scale error |Scale (Traj.) - 1| against its relative scale sigma on ``ax``, log-log,
    one marker per series (e.g. "chained", "own init"), with the lines error = sigma and error = 2 sigma: a
    calibrated sigma has about 95 % of the points below the 2-sigma line. Without any sigma, the axes say so."""
    points = {}
    for name, c in series.items():
        has = np.isfinite(c.rel_sigma) & (c.rel_sigma > 0)
        points[name] = (c.rel_sigma[has], c.errors[has])
    sigmas = np.concatenate([np.zeros(0), *(s for s, _ in points.values())])
    if sigmas.size:
        floor = 1e-5  # an exact scale (error 0) still gets a point, at the bottom of the log axis
        for (name, (s, e)), marker in zip(points.items(), "os^Dv"):
            if s.size:
                ax.scatter(s, np.maximum(e, floor), s=14, marker=marker, alpha=0.7, label=f"{name} ({s.size})")
        x = np.geomspace(sigmas.min() / 2.0, sigmas.max() * 2.0, 50)
        ax.plot(x, x, color="black", lw=1.0, label="error = sigma")
        ax.plot(x, 2.0 * x, color="black", lw=1.0, ls="--", label="error = 2 sigma")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.legend(fontsize=8, loc="upper left")
    else:
        ax.text(0.5, 0.5, NO_SIGMA, ha="center", va="center", wrap=True, transform=ax.transAxes)
    ax.set_xlabel("relative scale sigma (scale_sigma / scale)")
    ax.set_ylabel("scale error |Scale (Traj.) - 1|")
    ax.grid(alpha=0.3, which="both")


def save_sigma_plot(path: str | Path, series: dict[str, Claims], *, title: str = "") -> Path:
    """Write ``draw_sigma``'s figure of ``series`` as a PNG."""
    fig = Figure(figsize=(6.4, 5.6), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    draw_sigma(ax, series)
    ax.set_title(title or "scale error against its sigma (claimed clips)", fontsize=9)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png")
    return path
