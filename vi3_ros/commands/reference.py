"""``vi3 reference INPUT --poses TUM -o OUT``: a metric reference trajectory for a recording without ground truth.

``--poses`` is an offline reconstruction of the recording's camera (a TUM file of camera-to-world poses, up to one
unknown scale, in any world frame, stamped on the camera's clock as the frames are: COLMAP's structure from motion
of the frames, or any SLAM system's keyframes). The batch visual-inertial fit (``vi3_core.eval.reference``) gives
it its metric scale from the input's whole IMU record, with gravity, the biases and the camera-IMU time offset, and
fits each half of the record on its own as a check of the scale's sigma; ``--accel-intrinsics`` also fits the
accelerometer's scale factors and cross-axis terms (an uncalibrated IMU's, which otherwise pass into the scale).
``OUT`` receives the IMU body's metric poses in a gravity-aligned, z-up world at the reconstruction's stamps (the
camera's clock, as the frames are stamped), for ``vi3 eval INPUT --reference OUT``.

Exit status: 0 when the fit was made (OUT written); 2 for an input, poses file, calibration or output that cannot be
used; 130 / 143 when interrupted.
"""

from __future__ import annotations

import argparse
import math
import sys

from vi3_ros import interrupts


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("reference", help="give an offline reconstruction of a recording its metric scale from the "
                       "IMU; write a reference trajectory for vi3 eval --reference", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("input", help="ASL folder, make-bag folder, ROS 1 .bag, rosbag2 directory or .mcap (its IMU)")
    p.add_argument("--poses", required=True, metavar="TUM",
                   help="the reconstruction: camera-to-world poses up to scale, t tx ty tz qx qy qz qw per line, "
                        "stamped on the camera's clock")
    p.add_argument("--calib", help="EuRoC sensor.yaml or Kalibr camchain YAML (its T_cam_imu; default: the "
                   "input's own)")
    p.add_argument("--imu-topic", help="IMU topic of a bag (default: /imu0, else the only sensor_msgs/Imu topic)")
    p.add_argument("--time-offset", type=float, default=None, metavar="S",
                   help="camera stamp minus IMU stamp of one instant, s, when known (default: fitted)")
    p.add_argument("--accel-intrinsics", action="store_true",
                   help="also fit the accelerometer's scale factors and cross-axis terms (a 3x3 matrix; an "
                        "uncalibrated consumer IMU's reach several percent)")
    p.add_argument("--output", "-o", required=True, help="the metric reference, a TUM file (never over an input)")
    p.add_argument("--force", action="store_true", help="replace an existing --output")
    p.add_argument("--json", action="store_true", help="print the fit and its halves as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    with interrupts.trapped() as trap:
        try:
            from vi3_core.errors import Vi3Error

            fit, halves, n_poses = _fit(args)
        except KeyboardInterrupt:
            print(f"vi3 reference: interrupted by {trap.name}; nothing was written", file=sys.stderr)
            return trap.status
        except (Vi3Error, ValueError, OSError) as exc:
            print(f"vi3 reference: error: {exc}", file=sys.stderr)
            return 2
    a, b = halves
    z = (a.scale - b.scale) / math.hypot(a.scale_sigma, b.scale_sigma)
    if args.json:
        from vi3_core.eval.report import to_json

        print(to_json({**fit.as_dict(), "poses": n_poses, "halves": [a.as_dict(), b.as_dict()],
                       "halves_z": z, "output": str(args.output)}))
    else:
        print(f"vi3 reference: {fit.keyframes} of {n_poses} poses over {fit.span[1] - fit.span[0]:.1f} s: scale "
              f"{fit.scale:.6g} m per unit +- {100 * fit.rel_sigma:.2f} %, time offset {1e3 * fit.time_offset:+.1f} ms "
              f"(camera minus IMU), gyro bias {fit.bg.round(5).tolist()} rad/s, accelerometer bias "
              f"{fit.ba.round(3).tolist()} m/s^2 (walking {fit.accel_bias_walk:.3g} m/s^2/sqrt(s), up to "
              f"{fit.ba_spread:.3f} from that), IMU noise {fit.imu_noise_factor:.2f}x the model's, the "
              f"reconstruction's position noise {1e3 * fit.sigma_ref:.1f} mm, chi^2/dof {fit.chi2_dof:.2f}")
        if args.accel_intrinsics:
            rows = "; ".join(" ".join(f"{x:+.4f}" for x in row) for row in fit.accel_matrix)
            print(f"vi3 reference: accelerometer matrix (specific force = A x reading, rows) [{rows}], its elements "
                  f"+- {fit.accel_matrix_sigma.min():.4f}..{fit.accel_matrix_sigma.max():.4f}; for the node: "
                  f"--param accel_matrix=\"{' '.join(f'{x:.6f}' for x in fit.accel_matrix.ravel())}\"")
        print(f"vi3 reference: halves: {a.scale:.6g} +- {100 * a.rel_sigma:.2f} % and {b.scale:.6g} +- "
              f"{100 * b.rel_sigma:.2f} %: {abs(z):.1f} sigma apart; wrote {args.output}")
    return 0


def _fit(args: argparse.Namespace):
    """(the fit, its two halves, the poses read), the reference written to ``args.output``."""
    from vi3_core.dataset.asl import read_asl
    from vi3_core.dataset.calib import load_calib
    from vi3_core.errors import DataError
    from vi3_core.eval.reference import fit_halves, fit_reference
    from vi3_core.eval.tum import read_tum, write_tum
    from vi3_core.paths import check_output_file
    from vi3_ros.io.reader import (
        BAG_DAMAGE,
        DropEvent,
        ImuEvent,
        TopicRequest,
        find_calib,
        imu_samples,
        iter_events,
        resolve_input,
    )

    out = check_output_file(args.output, [args.input, args.poses, *([args.calib] if args.calib else [])],
                            what="vi3 reference --output", kind="a TUM file", force=args.force)
    path, kind = resolve_input(args.input)
    if args.calib or kind != "asl":
        found = args.calib or find_calib(path)
        calib = load_calib(found) if found is not None else None
    else:
        calib = read_asl(path).calib
    if calib is None:
        raise DataError(f"{args.input} carries no calibration; pass --calib (its T_cam_imu mounts the camera)")
    T_BC = calib.T_BC
    stamps, T_WC = read_tum(args.poses)
    imus = []
    for e in iter_events(args.input, imu=TopicRequest(args.imu_topic)):  # frames are let go as they come
        if isinstance(e, DropEvent) and e.reason in BAG_DAMAGE:
            raise DataError(f"{e.detail}; a reference is fitted to whole recordings")
        if isinstance(e, ImuEvent):
            imus.append(e)
    imu = imu_samples(imus)
    fit = fit_reference(stamps, T_WC, imu, T_BC, time_offset=args.time_offset, accel_intrinsics=args.accel_intrinsics)
    halves = fit_halves(stamps, T_WC, imu, T_BC, time_offset=fit.time_offset, accel_intrinsics=args.accel_intrinsics)
    inside = (stamps >= fit.span[0]) & (stamps <= fit.span[1])
    write_tum(out, stamps[inside], fit.body_track(stamps[inside], T_WC[inside], T_BC))
    return fit, halves, len(stamps)
