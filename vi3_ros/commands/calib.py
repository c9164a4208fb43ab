"""``vi3 calib INPUT``: the camera-IMU rig as a recording shows it, printed as a corrected Kalibr camchain-imucam YAML.

The node's pipeline runs over the input as ``vi3 replay`` does (same calibration, topics and parameters; ``init``
mode, the metric state carried across clips, self-calibration on) and writes nothing; at the end the rig's
self-calibration (``vi3_core.online.calibration``: the camera mount's rotation and the camera-IMU time offset from
the backbone's rotations against the gyro) corrects the configured calibration where it is sure: its sigma below
``calib_max_rotation_sigma`` / ``calib_max_offset_sigma``. The rest, and the intrinsics and the camera's position,
stay as configured. The YAML goes to stdout (or ``--output``) after comment lines that say what was estimated, what
was corrected and what the flight did not observe.

Exit status: 0 when the recording observed the rig (each part corrected, or confirmed within its tolerance); 1 when
it observed neither part well enough (the YAML is then the configuration as it was); 2 for an input, output or
configuration that cannot be used; 130 / 143 when interrupted.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from vi3_ros import interrupts


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calib", help="estimate the camera mount's rotation and the camera-IMU time offset from a "
                       "recording; print the corrected Kalibr YAML", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("input", help="ASL folder, make-bag folder, ROS 1 .bag, rosbag2 directory or .mcap")
    p.add_argument("--calib", help="EuRoC sensor.yaml or Kalibr camchain YAML to correct (parameter calib_file; "
                   "default: the input's own)")
    p.add_argument("--backbone", help="3D foundation model (parameter backbone)")
    p.add_argument("--device", help="torch device (parameter device)")
    p.add_argument("--params-file", help="ROS 2 parameter YAML, e.g. config/euroc.yaml")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", help="any node parameter")
    p.add_argument("--image-topic", help="camera topic to read (as vi3 replay)")
    p.add_argument("--imu-topic", help="IMU topic to read (as vi3 replay)")
    p.add_argument("--output", "-o", help="write the YAML here instead of stdout (never over an input)")
    p.add_argument("--force", action="store_true", help="replace an existing --output")
    p.add_argument("--json", action="store_true", help="print the estimate and the corrected values as JSON")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    with interrupts.trapped() as trap:
        try:
            from vi3_core.errors import Vi3Error
            from vi3_ros.params import settings_from_cli
            from vi3_ros.replay import replay_rig

            if args.output is not None:
                _check_output(args)
            settings = settings_from_cli(args.params_file, args.param, {
                "backbone": args.backbone, "calib_file": args.calib, "device": args.device})
            rig = replay_rig(args.input, settings=settings, progress=not args.no_progress and sys.stderr.isatty(),
                             image_topic=args.image_topic, imu_topic=args.imu_topic,
                             on_note=lambda note: print(f"vi3 calib: note: {note}", file=sys.stderr))
        except KeyboardInterrupt:
            print(f"vi3 calib: interrupted by {trap.name}; nothing was written", file=sys.stderr)
            return trap.status
        except (Vi3Error, ValueError, OSError) as exc:
            print(f"vi3 calib: error: {exc}", file=sys.stderr)
            return 2
        if rig.calib is None or rig.estimate is None:
            why = ("no camera calibration was configured or received" if rig.calib is None else
                   f"no clip reached the backbone ({rig.summary.why_nothing()})")
            print(f"vi3 calib: error: nothing to estimate from {args.input}: {why}", file=sys.stderr)
            return 2
        text = _json(rig) if args.json else _yaml(rig, args.input)
        try:
            if args.output is not None:
                Path(args.output).write_text(text)
            else:
                print(text, end="")
        except OSError as exc:
            print(f"vi3 calib: error: writing {args.output}: {exc.strerror or exc}", file=sys.stderr)
            return 2
        observed = rig.estimate.rotation_observed.all() or rig.estimate.offset_observed
        if not observed:
            print("vi3 calib: the recording observed neither the mount's rotation nor the time offset well enough "
                  f"({rig.estimate.describe()}): fly turns about more than one axis", file=sys.stderr)
        return 0 if observed else 1


def _check_output(args: argparse.Namespace) -> None:
    from vi3_core.paths import check_output_file

    check_output_file(args.output, [args.input, *([args.calib] if args.calib else [])], what="vi3 calib --output",
                      kind="a YAML file", force=args.force, empty_hint=" (or leave --output out for standard output)")


def _corrected(rig):
    """The configured calibration corrected by the estimate's sure parts (``RigEstimate.corrected``)."""
    import dataclasses

    T_BC, time_offset = rig.estimate.corrected(rig.calib.T_BC, rig.time_offset)
    return dataclasses.replace(rig.calib, T_BC=T_BC, time_offset=time_offset)


def _yaml(rig, source: str) -> str:
    from vi3_core.dataset.calib import corrected_kalibr, kalibr_camchain

    est = rig.estimate
    corrected = _corrected(rig)
    lines = [f"vi3 calib: the rig as {est.clips} clips of {source} show it ({rig.summary.bag_s:.1f} s)",
             est.describe(),
             (f"the configuration is off: {est.off_by()}" if est.off_by() else
              "the configuration agrees with the recording within its tolerance (calib_tolerance_*)"),
             ("T_cam_imu: rotation corrected" if est.rotation_applied else
              "T_cam_imu: as configured (the rotation is not observed well enough; fly turns about every axis)"),
             (f"timeshift_cam_imu: {rig.time_offset:+.5f} s configured, {corrected.time_offset:+.5f} s corrected"
              if est.offset_applied else
              f"timeshift_cam_imu: {rig.time_offset:+.5f} s as configured (the offset is not observed well enough)")]
    # the configured Kalibr file with the corrected fields replaced, every other field as it was
    text = corrected_kalibr(rig.calib_file, corrected) if rig.calib_file else None
    return "".join(f"# {line}\n" for line in lines) + (text or kalibr_camchain(corrected))


def _json(rig) -> str:
    from vi3_core import so3
    from vi3_core.eval.report import to_json

    corrected = _corrected(rig)
    return to_json({**rig.estimate.as_dict(), "off_by": rig.estimate.off_by(),
                    "configured_timeshift_cam_imu_s": rig.time_offset,
                    "corrected_timeshift_cam_imu_s": corrected.time_offset,
                    "corrected_T_cam_imu": so3.inv_T(corrected.T_BC).tolist(),
                    "replay": rig.summary.as_dict()}) + "\n"
