"""``vi3 make-bag OUT``: an EuRoC-format sequence with exact ground truth, written the ways EuRoC and its users
have it: ``OUT/asl/mav0/...`` (ASL folder, plus ground-truth depth in ``depth0/``), ``OUT/ros1.bag`` (ROS 1,
written with rosbags) and ``OUT/mcap/`` (rosbag2 MCAP converted from the ROS 1 bag with rosbags' converter), with
the camera calibration as a Kalibr ``OUT/camchain-imucam.yaml``.

Generated sequences fly a motion preset (``--motion``: easy, medium, difficult matched to EuRoC's statistics, or
agile) with an accelerometer bias of EuRoC's size unless ``--no-accel-bias``; ``--from-euroc MAV0_DIR`` renders
the scene along a real EuRoC ground-truth trajectory instead and carries its IMU samples unchanged. The same seed
gives identical image bytes and IMU values.

Everything is written into a hidden ``OUT/.vi3-generating.<pid>.*`` folder, a block of time at a time (memory
does not grow with the length), and moved into place only when complete: an error, Ctrl-C or SIGTERM leaves no
partial output, and a later run removes such folders left by runs that were killed. One run at a time writes OUT
(a second fails at once, naming the first), and a run that would not fit in the free disk space is refused before it
starts.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # vi3_core is imported where used: the CLI loads only what the command it runs needs
    from vi3_core.dataset.generate import Written

from vi3_ros import interrupts

OUTPUTS = ("asl", "ros1.bag", "mcap", "camchain-imucam.yaml")


def register(sub: argparse._SubParsersAction) -> None:
    from vi3_core.dataset.generate import CAMERAS
    from vi3_core.render.scene import SCENES
    from vi3_core.sim.trajectory import MOTIONS

    p = sub.add_parser("make-bag", help="generate an EuRoC-format sequence (ASL, ROS 1 bag, rosbag2 MCAP)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", help="output folder")
    p.add_argument("--seconds", type=float, default=None,
                   help="duration in seconds (default 20; with --from-euroc: all the recording covers)")
    p.add_argument("--seed", type=int, default=0, help="random seed: scene, trajectory, IMU noise (default 0)")
    p.add_argument("--scene", default="room", choices=sorted(SCENES), help="scene (default room)")
    p.add_argument("--motion", default=None, choices=MOTIONS,
                   help="motion preset: easy, medium, difficult (EuRoC-like, see docs/evaluation.md), handheld (a "
                        "camera carried around a room) or agile (slow drift with quick small manoeuvres); default "
                        "medium")
    p.add_argument("--camera", default="euroc", choices=CAMERAS,
                   help="camera: euroc (EuRoC's cam0, rendered ideally; default) or realsense (1280x720 through what a "
                        "real sensor does: rolling shutter, motion blur, auto exposure and its frame rates, lost "
                        "frames, noise, JPEG; its IMU's noise, merged streams and a clock 53 ms off the frames')")
    p.add_argument("--no-accel-bias", action="store_true",
                   help="zero initial accelerometer bias (default: 0.05-0.2 m/s^2 in a random direction)")
    p.add_argument("--noise-free-imu", action="store_true",
                   help="IMU without noise, bias random walk or vibration (constant biases)")
    p.add_argument("--from-euroc", metavar="MAV0_DIR", default=None,
                   help="render along this real EuRoC recording's ground truth and carry its IMU unchanged "
                        "(needs imu0/, state_groundtruth_estimate0/ and cam0/sensor.yaml; no images)")
    p.add_argument("--start", type=float, default=0.0,
                   help="with --from-euroc: start the camera stream this many seconds into the recording (default 0)")
    p.add_argument("--no-depth", action="store_true", help="skip the ground-truth depth maps (faster, smaller)")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs in OUT")
    p.set_defaults(func=run)


def make_bag(out, spec, *, overwrite: bool = False, workers: int = 2) -> tuple[dict[str, float], Written]:
    """Write the three forms of the sequence ``spec`` (a ``SequenceSpec``) into ``out``; returns the seconds each
    stage took and what ``write_sequence`` reports. Raises DataError for an output that cannot be written: a file,
    outputs already there (without ``overwrite``), another run writing it (``OutputLock``), a folder that is or holds
    the recording to follow, or too little free space (``check_space``)."""
    from vi3_core.dataset.calib import write_kalibr_camchain
    from vi3_core.dataset.generate import staging_dir, write_sequence
    from vi3_core.errors import DataError
    from vi3_core.paths import check_apart
    from vi3_ros.io.convert import convert_to_rosbag2
    from vi3_ros.io.output_lock import OutputLock
    from vi3_ros.io.ros1 import Ros1BagWriter
    from vi3_ros.io.topics import IMAGE_TOPIC

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise DataError(f"{out}: is a file; make-bag writes a folder")
    if spec.from_euroc is not None:
        check_apart(out, [spec.from_euroc], what="make-bag output")
    out.parent.mkdir(parents=True, exist_ok=True)
    with OutputLock(out, what="make-bag output"):
        existing = [name for name in OUTPUTS if (out / name).exists()]
        if existing and not overwrite:
            raise DataError(f"{out}: already holds {', '.join(existing)}; pass --overwrite to replace them")
        check_space(out, spec)
        created = not out.exists()
        stage = staging_dir(out)
        times = {}
        try:
            t = time.perf_counter()
            with Ros1BagWriter(stage / "ros1.bag") as bag:
                written = write_sequence(stage / "asl" / "mav0", spec, workers=workers, on_block=lambda b: bag.write(
                    b.cam_ns, b.images.__getitem__, b.imu_ns, b.imu, b.gt_ns, b.T_WB))
            times["asl_and_ros1_s"] = time.perf_counter() - t
            t = time.perf_counter()
            convert_to_rosbag2(stage / "ros1.bag", stage / "mcap", storage="mcap")
            times["mcap_s"] = time.perf_counter() - t
            write_kalibr_camchain(written.calib, stage / "camchain-imucam.yaml", rostopic=IMAGE_TOPIC)
            interrupts.hold()  # the outputs are moved into place whole: a signal now is reported after the move
            for name in OUTPUTS:
                target = out / name
                if target.is_dir():
                    shutil.rmtree(target)
                elif target.exists():
                    target.unlink()
                os.rename(stage / name, target)
        finally:
            shutil.rmtree(stage, ignore_errors=True)
            if created and out.is_dir() and not any(out.iterdir()):
                out.rmdir()
    return times, written


#: Bytes make-bag writes per camera frame, in units of its raw mono8 image (width x height): the image in the ROS 1
#: bag and again in the MCAP, its PNG (about 0.55 on rendered scenes) and, with depth, the depth PNG (about 0.3).
#: The IMU and ground-truth rows are small beside them.
BYTES_PER_PIXEL = 2.6
DEPTH_BYTES_PER_PIXEL = 0.4


def check_space(out: Path, spec) -> None:
    """DataError, before anything is written, when the file system of ``out`` has less free space than a generated
    sequence ``spec`` needs (an estimate; a sequence rendered along a recording is bounded by it and not checked)."""
    from vi3_core.dataset.generate import CAM_PERIOD_NS, EUROC_CAM0
    from vi3_core.errors import DataError

    if spec.from_euroc is not None:
        return
    w, h = EUROC_CAM0.size
    frames = spec.seconds * 1e9 / CAM_PERIOD_NS + 1
    needed = frames * w * h * (BYTES_PER_PIXEL + (DEPTH_BYTES_PER_PIXEL if spec.with_depth else 0.0))
    free = shutil.disk_usage(next(p for p in (out, *out.parents) if p.exists())).free
    if needed > free:
        raise DataError(f"{out}: {spec.seconds:g} s of sequence need about {needed / 1e9:.3g} GB, and its file system "
                        f"has {free / 1e9:.3g} GB free; choose fewer --seconds (or --no-depth) or another folder")


def _spec(args: argparse.Namespace):
    from vi3_core.dataset.generate import SequenceSpec
    from vi3_core.errors import DataError

    if args.from_euroc is not None:
        given = [flag for flag, on in (("--motion", args.motion is not None), ("--no-accel-bias", args.no_accel_bias),
                                       ("--noise-free-imu", args.noise_free_imu),
                                       ("--camera", args.camera != "euroc")) if on]
        if given:
            raise DataError(f"{', '.join(given)}: only for generated sequences; --from-euroc carries the "
                            "recording's own IMU and motion")
    return SequenceSpec(seconds=args.seconds if args.seconds is not None or args.from_euroc else 20.0,
                        seed=args.seed, scene=args.scene, motion=args.motion or "medium",
                        accel_bias=not args.no_accel_bias, imu_noise=not args.noise_free_imu,
                        with_depth=not args.no_depth, from_euroc=args.from_euroc, start_s=args.start,
                        camera=args.camera)


def run(args: argparse.Namespace) -> int:
    from vi3_core.dataset.generate import MAX_GT_GAP_NS
    from vi3_core.errors import DataError

    def fail(reason: str, code: int = 2) -> int:
        print(f"vi3 make-bag: error: {reason}", file=sys.stderr)
        return code

    t0 = time.perf_counter()
    with interrupts.trapped() as trap:  # the first signal unwinds the run, which removes what it wrote
        try:
            times, written = make_bag(args.out, _spec(args), overwrite=args.overwrite)
        except DataError as err:
            return fail(str(err))
        except OSError as err:  # a read-only folder, a full disk, an unreadable recording
            path = Path(err.filename) if err.filename else Path(args.out)
            verb = "cannot write" if Path(args.out) in (path, *path.parents) else "cannot read"
            return fail(f"{verb} {path}: {err.strerror or err}")
        except KeyboardInterrupt:
            return fail(f"interrupted by {trap.name}; nothing written (partial output removed)", trap.status)
        if trap.signum is not None:
            return fail(f"interrupted by {trap.name} after the outputs were complete in {args.out}", trap.status)
    stages = ", ".join(f"{k[:-2].replace('_', ' ')} {v:.1f} s" for k, v in times.items())
    print(f"wrote {args.out}/asl/mav0, {args.out}/ros1.bag, {args.out}/mcap/ and {args.out}/camchain-imucam.yaml "
          f"in {time.perf_counter() - t0:.1f} s ({stages})")
    for ns0, ns1 in written.gt_gaps.tolist():
        print(f"vi3 make-bag: note: no frames in the ground truth's gap of {(ns1 - ns0) * 1e-9:.3f} s from {ns0} to "
              f"{ns1} ns (GT rows more than {MAX_GT_GAP_NS * 1e-9:g} s apart)", file=sys.stderr)
    return 0
