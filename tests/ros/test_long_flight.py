"""An hour of flight through the odom chain, ``~/odom``, ``~/path`` and ``~/odom/imu`` (issue 39): on a real 124 s
recording the chain's rotations drifted from orthonormal by 1.7e-6 per clip (a Kalibr ``T_cam_imu`` written to 8
digits, composed twice per clip), and from 100 s of chained odometry on every output failed its message's rotation
check. Here an hour of generated flight, with the inputs as a real rig gives them (a mount rotation written to 6
digits, float32 poses from the backbone), is chained clip by clip and propagated sample by sample; every message must
build and every pose stay a rotation to 1e-9."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from msg_adapters.types import jazzy_types
from vi3_core import so3
from vi3_core.init import InitOptions
from vi3_core.online import OdomChain, OnlineOptions
from vi3_core.online.stream import ClipOutcome
from vi3_core.sim.imu import ImuNoise, imu_stamps, simulate_imu
from vi3_core.sim.trajectory import make_trajectory
from vi3_core.types import (
    AnchorResult,
    Clip,
    Geometry,
    ImuSamples,
    ImuTrajectory,
    InitResult,
    InitStatus,
    ScaleFit,
)
from vi3_ros.imu_odom import ImuOdometry
from vi3_ros.outputs import ClipPublisher
from vi3_ros.params import resolve

pytestmark = pytest.mark.slow  # an hour of odometry: about 15 s of CPU

HOUR_S = 3600.0
IMU_HZ = 50.0  # the rate does not matter to round-off per composition; fewer samples keep the test short
FRAME_S, CLIP_FRAMES = 0.1, 8  # clips of 8 frames, each starting with the last frame of the one before
SCALE = 3.0  # metres per model unit of the "backbone"
G_W = np.array([0.0, 0.0, -9.81])


class _Checked:
    """The sink: every message's pose must be finite with a unit quaternion (and a path's every pose)."""

    def __init__(self) -> None:
        self.counts: dict[str, int] = {}
        self.worst = 0.0

    def publish(self, key: str, msg, stamp_ns: int) -> None:
        self.counts[key] = self.counts.get(key, 0) + 1
        poses = [p.pose for p in msg.poses] if key == "path" else [msg.pose.pose]
        for pose in poses:
            q = np.array([pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w])
            p = np.array([pose.position.x, pose.position.y, pose.position.z])
            assert np.isfinite(q).all() and np.isfinite(p).all(), (key, stamp_ns)
            self.worst = max(self.worst, abs(float(np.linalg.norm(q)) - 1.0))


def _since(imu: ImuSamples, fed: int, t: float) -> ImuSamples:
    """The first ``fed`` samples of ``imu`` (what the node has received) from the last one at or before ``t`` s."""
    return imu.select(np.arange(int(np.searchsorted(imu.t[:fed], t, side="right")) - 1, fed))


def _rounded_mount() -> np.ndarray:
    """A camera mount as a calibration file gives it: a rotation written to 6 digits (1e-6 from orthonormal)."""
    T = so3.make_T(so3.exp(np.array([1.2, -1.1, 1.3])), np.array([-0.02, 0.06, 0.01]))
    return np.round(T, 6)


def test_an_hour_of_chained_and_propagated_odometry_stays_rotations():
    traj = make_trajectory("drone", seed=5, motion="medium")
    imu = simulate_imu(traj, imu_stamps(0.0, HOUR_S + 1.0, IMU_HZ), noise=ImuNoise(), seed=1).samples
    T_BC = _rounded_mount()
    assert so3.orthonormality_error(T_BC[:3, :3]) > 1e-7
    settings = resolve({"imu_odom_rate": IMU_HZ, "path_max_poses": 20})
    init_options = InitOptions()
    chain = OdomChain(options=OnlineOptions(), init_options=init_options)
    sink = _Checked()
    types = jazzy_types()
    publisher = ClipPublisher(settings, types=types, publish=sink.publish)
    imu_odom = ImuOdometry(settings, types=types, publish=sink.publish)
    K = np.array([[400.0, 0.0, 320.0], [0.0, 400.0, 240.0], [0.0, 0.0, 1.0]])
    hop = CLIP_FRAMES - 1
    n_clips = int((HOUR_S - 1.0) / (hop * FRAME_S))
    fed = int(np.searchsorted(imu.t, 0.5 + hop * FRAME_S, side="right"))  # samples fed before the first clip lands
    for k in range(n_clips):
        stamps = (k * hop + np.arange(CLIP_FRAMES)) * FRAME_S + 0.5
        i0, i1 = np.searchsorted(imu.t, [stamps[0] - 2.0, stamps[-1]], side="right")
        clip_imu = imu.select(np.arange(max(i0 - 1, 0), i1 + 1))
        clip = Clip(stamps, np.zeros((CLIP_FRAMES, 1, 1), np.uint8), K, T_BC, clip_imu,
                    stamps_ns=np.round(stamps * 1e9).astype(np.int64))
        T_WB = traj.T_WB(stamps)
        R_B1W = T_WB[0, :3, :3].T
        T_WC = T_WB @ T_BC
        T_wc = np.linalg.inv(T_WC[0]) @ T_WC
        T_wc[:, :3, 3] /= SCALE
        T_wc = T_wc.astype(np.float32).astype(np.float64)  # a backbone's float32 poses, 6e-8 from orthonormal
        geometry = Geometry(T_wc, np.repeat(K[None], CLIP_FRAMES, 0), np.ones((CLIP_FRAMES, 1, 1)),
                            np.ones((CLIP_FRAMES, 1, 1)))
        v_B1 = traj.velocity_W(stamps) @ R_B1W.T
        target = ImuTrajectory(R=R_B1W @ T_WB[:, :3, :3], p=(T_WB[:, :3, 3] - T_WB[0, :3, 3]) @ R_B1W.T, v=v_B1,
                               T_wc=geometry.T_wc)
        fit = ScaleFit(lam=1 / SCALE, scale_rel_sigma=0.02, v1=v_B1[0], v1_sigma=0.02, g_sigma=0.005, sigma_v=0.001,
                       dof=20.0, variance_factor=1.0, settled=True)
        init = InitResult(InitStatus.OK, "ok", bg=np.zeros(3), g=R_B1W @ G_W, scale=SCALE, scale_sigma=0.02 * SCALE,
                          v1=v_B1[0], target=target, fit=fit)
        result = AnchorResult(geometry.scaled(SCALE), geometry, init, "init", SCALE, target=target)
        chained = chain.add(clip, result, clip_imu)
        assert chained is not None, k
        outcome = ClipOutcome(clip, init, result, chained=chained, state=chain.state)
        publisher.odom(clip, outcome, chain.trajectory)
        assert publisher.take_errors() == [], k
        # the clip lands once its last frame's IMU came: the propagation catches up from the buffer, then takes the
        # samples until the next clip lands one by one, as the node feeds them
        imu_odom.restart(chain.state, functools.partial(_since, imu, fed))
        end = int(np.searchsorted(imu.t, stamps[-1] + hop * FRAME_S, side="right"))
        for j in range(fed, end):
            imu_odom.add(round(imu.t[j] * 1e9), imu.gyro[j], imu.accel[j])
        fed = end
    assert chain.trajectory.stamps[-1] > HOUR_S - 2.0 and len(chain.trajectory.resets) == 0
    assert so3.orthonormality_error(chain.trajectory.T_OB[:, :3, :3]) < 1e-9
    assert sink.counts["odom"] == sink.counts["path"] == n_clips
    assert sink.counts["odom_imu"] >= 0.95 * fed and imu_odom.status == "running"
    assert sink.worst < 1e-9
    # the chain follows the flight: metres per hour of motion, within the propagation of a few centimetres per clip
    truth = traj.position_W(chain.trajectory.stamps[-1:])[0] - traj.position_W(chain.trajectory.stamps[:1])[0]
    flown = chain.trajectory.T_OB[-1, :3, 3] - chain.trajectory.T_OB[0, :3, 3]
    assert abs(np.linalg.norm(flown) - np.linalg.norm(truth)) < 1.0 + 0.01 * math.hypot(*truth)
