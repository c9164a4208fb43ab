"""Generate an EuRoC-format ASL sequence with exact ground truth: trajectory + IMU + rendering + GT depth.

The drone flies ``vi3_core.sim.trajectory.make_trajectory("drone", seed)`` inside the scene's free volume;
cam0 (EuRoC's intrinsics, radial-tangential distortion and ``T_BS``) renders mono8 at 20 Hz; the IMU
(``simulate_imu``, EuRoC noise, random initial gyro bias) and the ground-truth state run at 200 Hz on the same
nanosecond grid, so camera stamps coincide with IMU and GT stamps, as in EuRoC.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from vi3_core.dataset import asl
from vi3_core.dataset.calib import CameraCalib
from vi3_core.render.raycast import Renderer
from vi3_core.render.scene import make_scene
from vi3_core.sim import euroc
from vi3_core.sim.imu import ImuNoise, simulate_imu
from vi3_core.sim.trajectory import make_trajectory

#: EuRoC cam0 (MH_01 ``cam0/sensor.yaml``): intrinsics, radial-tangential distortion, T_BS, 752x480 @ 20 Hz.
EUROC_CAM0 = CameraCalib(K=euroc.K_cam0(), dist_model="radtan", dist=np.array(euroc.DISTORTION_CAM0),
                         size=euroc.RESOLUTION_CAM0, T_BC=euroc.T_BS_CAM0.copy(), rate_hz=euroc.CAMERA_RATE_HZ)

T0_NS = 1_700_000_000_000_000_000  # first camera stamp (ns): EuRoC-like epoch stamps
CAM_PERIOD_NS = 50_000_000  # 20 Hz
IMU_PERIOD_NS = 5_000_000  # 200 Hz
IMU_MARGIN_NS = 100_000_000  # IMU and GT start 0.1 s before the first frame and end 0.1 s after the last


def generate_sequence(out_dir, *, seconds: float = 4.0, seed: int = 0, scene: str = "room",
                      imu_noise: bool = True, with_depth: bool = True, workers: int = 2) -> Path:
    """Write an ASL sequence to ``out_dir/mav0`` and return ``out_dir`` (cached).

    If ``out_dir`` already holds a complete sequence generated with the same parameters it is reused. The
    sequence is written to a temporary folder inside ``out_dir`` first and renamed, so concurrent callers are safe.
    ``imu_noise=False`` writes noise-free IMU with constant biases (for exact inertial checks);
    ``workers`` threads render and encode frames (numpy and OpenCV release the GIL).
    """
    out_dir = Path(out_dir)
    params = {"seconds": float(seconds), "seed": int(seed), "scene": scene, "imu_noise": bool(imu_noise),
              "with_depth": bool(with_depth), "version": 1}
    marker = out_dir / "mav0" / "vi3_generated.json"
    if _matches(marker, params):
        return out_dir
    out_dir.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".vi3-generating.", dir=out_dir))
    try:
        _write(tmp / "mav0", seconds=seconds, seed=seed, scene=scene, imu_noise=imu_noise,
               with_depth=with_depth, workers=workers)
        (tmp / "mav0" / "vi3_generated.json").write_text(json.dumps(params))
        if _matches(marker, params):  # another process finished the same sequence meanwhile
            return out_dir
        shutil.rmtree(out_dir / "mav0", ignore_errors=True)  # a sequence made with other parameters
        try:
            os.rename(tmp / "mav0", out_dir / "mav0")
        except OSError:
            if not _matches(marker, params):
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out_dir


def _matches(marker: Path, params: dict) -> bool:
    try:
        return json.loads(marker.read_text()) == params
    except (OSError, ValueError):
        return False


def cached_sequence(cache_dir, *, seconds: float = 4.0, seed: int = 0, scene: str = "room",
                    imu_noise: bool = True, with_depth: bool = True) -> Path:
    """``generate_sequence`` into ``cache_dir/<key>`` where the key names every parameter."""
    key = f"{scene}_seed{seed}_{seconds:g}s{'' if imu_noise else '_noisefree'}{'' if with_depth else '_nodepth'}"
    return generate_sequence(Path(cache_dir) / key, seconds=seconds, seed=seed, scene=scene,
                             imu_noise=imu_noise, with_depth=with_depth)


def _write(mav0: Path, *, seconds: float, seed: int, scene: str, imu_noise: bool, with_depth: bool,
           workers: int) -> None:
    world = make_scene(scene, seed)
    traj = make_trajectory("drone", seed, center=tuple(world.center), extent=tuple(world.extent))
    calib = EUROC_CAM0
    n_frames = int(round(seconds * 1e9 / CAM_PERIOD_NS)) + 1
    cam_ns = T0_NS + np.arange(n_frames, dtype=np.int64) * CAM_PERIOD_NS
    imu_ns = np.arange(cam_ns[0] - IMU_MARGIN_NS, cam_ns[-1] + IMU_MARGIN_NS + 1, IMU_PERIOD_NS, dtype=np.int64)
    rng = np.random.default_rng([seed, 3])
    bg0 = rng.uniform(-0.03, 0.03, size=3)  # rad/s, EuRoC-sized initial gyro bias
    noise = ImuNoise() if imu_noise else ImuNoise.zero()
    # The trajectory's clock starts at the first IMU sample; stamps are exact on the ns grid.
    t_imu = (imu_ns - imu_ns[0]) * 1e-9
    sim = simulate_imu(traj, t_imu, noise=noise, bg0=bg0, ba0=np.zeros(3), seed=seed)
    imu = type(sim.samples)(imu_ns * 1e-9, sim.samples.gyro, sim.samples.accel)
    asl.write_imu(mav0, imu_ns, imu, noise=noise)
    asl.write_groundtruth(mav0, imu_ns, traj.T_WB(t_imu), traj.velocity_W(t_imu), sim.bg, sim.ba)

    renderer = Renderer(world, calib)
    img_dir = asl.write_camera(mav0, calib, cam_ns)
    depth_dir = asl.write_depth_meta(mav0, cam_ns, calib.undistorter().K) if with_depth else None
    T_WC = traj.T_WB((cam_ns - imu_ns[0]) * 1e-9) @ calib.T_BC

    def frame(i: int) -> None:
        image, depth = renderer.render(T_WC[i], with_depth=with_depth)
        asl.write_image(img_dir, cam_ns[i], image)
        if depth_dir is not None:
            asl.write_depth(depth_dir, cam_ns[i], depth)

    with ThreadPoolExecutor(max(workers, 1)) as pool:
        list(pool.map(frame, range(n_frames)))
