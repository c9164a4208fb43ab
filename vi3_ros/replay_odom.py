"""The odometry a replay wrote, read back from its output and scored against a sequence's ground truth.

``read_odometry(OUT)`` reads ``~/path`` (its last message: the chained odom trajectory, every frame once), ``~/status``
(the odom segment of each clip, the window resets) and ``~/odom/imu`` (the IMU-rate odometry) of a ``vi3 replay``
output. ``odometry_report`` scores the trajectory with ``vi3_core.eval.chained`` (4-DoF alignment per segment, ATE,
gravity error; drift: the segments' final position errors per metre flown) and the IMU-rate odometry's rate and its
jumps at the corrections (a clip landing), each against the 1-sigma the message before it claimed.

Clips a busy worker dropped leave seconds between the chained clips, so the metres flown are the ground truth's path
length over each segment's time span, not the sum of the straight lines between its chained frames (``vi3 eval``
chains contiguous clips, where the two agree).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader

from msg_adapters.diagnostics import diagnostic_array_to_statuses
from msg_adapters.poses import odometry_to_numpy, poses_to_T
from msg_adapters.stamps import stamp_to_ns
from vi3_core.dataset.sequence import GroundTruthTrack
from vi3_core.eval.chained import chained_metrics, gt_path_length
from vi3_core.types import window_bounds
from vi3_ros.outputs import OUTPUTS, STATUS_NAME
from vi3_ros.replay import topic_name


@dataclass
class ReplayOdometry:
    """path_ns [N] int ns, path_T [N,4,4]: the chained trajectory (body poses in odom, header stamps); segment_starts:
    first stamps (s, IMU time) of the clips that started a new odom segment; window_resets: the ``reset: ...``
    reasons of the online window; imu_ns [M], imu_T [M,4,4], imu_v [M,3] (odom, m/s), imu_pose_cov [M,6,6]: the
    ``~/odom/imu`` messages in stamp order."""

    path_ns: np.ndarray
    path_T: np.ndarray
    segment_starts: list[float]
    window_resets: list[str]
    imu_ns: np.ndarray
    imu_T: np.ndarray
    imu_v: np.ndarray
    imu_pose_cov: np.ndarray


def read_odometry(output: str | Path) -> ReplayOdometry:
    """The odometry outputs of a replay output (``OUT.mcap`` or a rosbag2 directory)."""
    topics = {key: topic_name(OUTPUTS[key].topic) for key in ("path", "status", "odom_imu")}
    last_path, imu, segments, resets = None, [], {}, []
    with AnyReader([Path(output)]) as reader:
        conns = [c for c in reader.connections if c.topic in topics.values()]
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.topic == topics["path"]:
                last_path = msg
            elif conn.topic == topics["odom_imu"]:
                imu.append((stamp_to_ns(msg.header.stamp), *odometry_to_numpy(msg)))
            else:
                for s in diagnostic_array_to_statuses(msg):
                    if s.name == STATUS_NAME and "odom_segment_start" in s.values:
                        segments.setdefault(int(s.values["odom_segment"]), float(s.values["odom_segment_start"]))
                    if "reset: " in s.values.get("online", ""):
                        resets.append(s.values["online"].split("reset: ", 1)[1])
    poses = [] if last_path is None else last_path.poses
    imu.sort(key=lambda row: row[0])
    return ReplayOdometry(
        path_ns=np.array([stamp_to_ns(p.header.stamp) for p in poses], dtype=np.int64),
        path_T=poses_to_T([p.pose for p in poses]) if poses else np.zeros((0, 4, 4)),
        segment_starts=[t for k, t in sorted(segments.items()) if k > 0], window_resets=resets,
        imu_ns=np.array([r[0] for r in imu], dtype=np.int64),
        imu_T=np.array([r[1] for r in imu]).reshape(-1, 4, 4),
        imu_v=np.array([r[1][:3, :3] @ r[2] for r in imu]).reshape(-1, 3),
        imu_pose_cov=np.array([r[4] for r in imu]).reshape(-1, 6, 6))


def correction_jumps(odo: ReplayOdometry) -> tuple[np.ndarray, np.ndarray, int]:
    """At each correction of a running ``~/odom/imu`` (where the propagation restarts from a newly chained clip: the
    pose covariance shrinks, and the previous message is at most two message intervals older), the jump (m): the new
    position minus the previous message's position carried forward with its velocity; and that previous message's
    position 1-sigma (m, 3D). Both [c]; and the count of resumes, restarts after the stream had stopped (a longer
    silence: ``imu_odom_max_sigma``, an IMU gap), which are no jump of a running stream."""
    var = np.trace(odo.imu_pose_cov[:, :3, :3], axis1=1, axis2=2)
    k = np.flatnonzero(np.diff(var) < 0)  # message k + 1 starts from a new state
    gaps = np.diff(odo.imu_ns)
    running = gaps[k] <= 2 * np.median(gaps) if len(gaps) else np.zeros(0, bool)
    resumes = int((~running).sum())
    k = k[running]
    dt = (odo.imu_ns[k + 1] - odo.imu_ns[k]) * 1e-9
    predicted = odo.imu_T[k, :3, 3] + odo.imu_v[k] * dt[:, None]
    return np.linalg.norm(odo.imu_T[k + 1, :3, 3] - predicted, axis=1), np.sqrt(var[k]), resumes


def odometry_report(odo: ReplayOdometry, gt: GroundTruthTrack | None, *, time_offset: float = 0.0) -> dict[str, Any]:
    """JSON-ready: ``odom`` (the chained trajectory's frames, segments, window resets and, with ``gt``, its chained
    metrics), ``imu_odom`` (messages, median rate in Hz, corrections, the largest jump and jump / sigma).
    ``time_offset``: the replay's parameter (header stamps are camera time; ground truth is in IMU time)."""
    odom: dict[str, Any] = {"frames": len(odo.path_ns), "segments": len(odo.segment_starts) + bool(len(odo.path_ns)),
                            "window_resets": len(odo.window_resets)}
    t = odo.path_ns * 1e-9 + time_offset
    if gt is not None and len(t) >= 2:
        i0, i1 = window_bounds(t, gt.t[0], gt.t[-1], 0)
        inside = slice(i0, i1)
        m = chained_metrics(odo.path_T[inside], gt.at(t[inside]).T_WB, stamps=t[inside],
                            segment_starts=odo.segment_starts, path_length=functools.partial(gt_path_length, gt))
        odom.update(ate_m=round(m.ate_m, 4), drift_pct=round(m.drift_pct, 3) if m.distance_m > 0 else None,
                    gravity_err_deg=round(m.gravity_err_deg, 3), distance_m=round(m.distance_m, 2),
                    scored_frames=m.frames)
    jumps, sigmas, resumes = correction_jumps(odo)
    rate = 1e9 / float(np.median(np.diff(odo.imu_ns))) if len(odo.imu_ns) >= 2 else None
    imu = {"messages": len(odo.imu_ns), "rate_hz": None if rate is None else round(rate, 1),
           "corrections": len(jumps), "resumes": resumes,
           "max_jump_m": round(float(jumps.max()), 4) if len(jumps) else None,
           "max_jump_sigma": round(float((jumps / sigmas).max()), 2) if len(jumps) else None}
    return {"odom": odom, "imu_odom": imu}
