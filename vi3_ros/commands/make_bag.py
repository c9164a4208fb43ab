"""``vi3 make-bag OUT``: generate an EuRoC-format sequence with exact ground truth and write it the ways EuRoC and
its users do: ``OUT/asl/mav0/...`` (ASL folder, plus ground-truth depth in ``depth0/``), ``OUT/ros1.bag`` (ROS 1,
written with rosbags) and ``OUT/mcap/`` (rosbag2 MCAP converted from the ROS 1 bag with rosbags' converter), with
the camera calibration as a Kalibr ``OUT/camchain-imucam.yaml``. The same seed gives identical image bytes and IMU
values.
"""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    from vi3_core.render.scene import SCENES

    p = sub.add_parser("make-bag", help="generate an EuRoC-format sequence (ASL, ROS 1 bag, rosbag2 MCAP)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", help="output folder")
    p.add_argument("--seconds", type=float, default=20.0, help="duration in seconds (default 20)")
    p.add_argument("--seed", type=int, default=0, help="random seed: scene, trajectory, IMU noise (default 0)")
    p.add_argument("--scene", default="room", choices=sorted(SCENES), help="scene (default room)")
    p.add_argument("--no-depth", action="store_true", help="skip the ground-truth depth maps (faster, smaller)")
    p.add_argument("--noise-free-imu", action="store_true", help="IMU without noise or bias random walk")
    p.add_argument("--overwrite", action="store_true", help="replace existing bags in OUT")
    p.set_defaults(func=run)


def make_bag(out, *, seconds: float, seed: int, scene: str = "room", with_depth: bool = True,
             imu_noise: bool = True, overwrite: bool = False) -> dict[str, float]:
    """Write the three forms of one sequence into ``out``; returns the seconds each stage took."""
    from vi3_core.dataset.calib import write_kalibr_camchain
    from vi3_core.dataset.generate import EUROC_CAM0, generate_sequence
    from vi3_core.errors import DataError
    from vi3_ros.io.convert import convert_to_rosbag2
    from vi3_ros.io.ros1 import write_ros1_bag
    from vi3_ros.io.topics import IMAGE_TOPIC

    out = Path(out)
    bag, mcap = out / "ros1.bag", out / "mcap"
    if bag.exists() or mcap.exists():
        if not overwrite:
            raise DataError(f"{out}: already holds ros1.bag or mcap/; pass --overwrite to replace them")
        bag.unlink(missing_ok=True)
        shutil.rmtree(mcap, ignore_errors=True)
    times = {}
    t = time.perf_counter()
    generate_sequence(out / "asl", seconds=seconds, seed=seed, scene=scene, imu_noise=imu_noise,
                      with_depth=with_depth)
    times["asl_s"] = time.perf_counter() - t
    t = time.perf_counter()
    write_ros1_bag(out / "asl", bag)
    times["ros1_bag_s"] = time.perf_counter() - t
    t = time.perf_counter()
    convert_to_rosbag2(bag, mcap, storage="mcap")
    times["mcap_s"] = time.perf_counter() - t
    write_kalibr_camchain(EUROC_CAM0, out / "camchain-imucam.yaml", rostopic=IMAGE_TOPIC)
    return times


def run(args: argparse.Namespace) -> int:
    from vi3_core.errors import DataError

    t0 = time.perf_counter()
    try:
        times = make_bag(args.out, seconds=args.seconds, seed=args.seed, scene=args.scene,
                         with_depth=not args.no_depth, imu_noise=not args.noise_free_imu, overwrite=args.overwrite)
    except DataError as err:
        print(f"vi3 make-bag: error: {err}")
        return 2
    stages = ", ".join(f"{k[:-2]} {v:.1f} s" for k, v in times.items())
    print(f"wrote {args.out}/asl/mav0, {args.out}/ros1.bag, {args.out}/mcap/ and {args.out}/camchain-imucam.yaml "
          f"in {time.perf_counter() - t0:.1f} s ({stages})")
    return 0
