"""``vi3 replay INPUT --output OUT.mcap``: run the node's pipeline over a recorded sequence (see vi3_ros.replay)."""

from __future__ import annotations

import argparse
import sys

from vi3_core.errors import Vi3Error
from vi3_ros import interrupts


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("replay", help="replay a bag or ASL folder through the node's pipeline into an MCAP",
                       description="Drives the same clip buffer, worker and anchoring as vi3_node in bag time and "
                       "writes what the node would publish. Parameters: docs/node.md.")
    p.add_argument("input", help="ASL folder, make-bag folder, ROS 1 .bag, rosbag2 directory or .mcap")
    p.add_argument("--output", "-o", required=True, help="OUT.mcap (one MCAP file) or a rosbag2 directory name")
    p.add_argument("--backbone", help="3D foundation model (parameter backbone)")
    p.add_argument("--mode", help="refinement after the fast init result (parameter mode)")
    p.add_argument("--calib", help="EuRoC sensor.yaml or Kalibr camchain YAML (parameter calib_file)")
    p.add_argument("--device", help="torch device (parameter device)")
    p.add_argument("--params-file", help="ROS 2 parameter YAML, e.g. config/euroc.yaml")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", help="any node parameter")
    p.add_argument("--image-topic", help="camera topic to read (sensor_msgs/Image or CompressedImage; default: the "
                   "parameter image_topic when the input has it, else the only image topic)")
    p.add_argument("--imu-topic", help="IMU topic to read (default: the parameter imu_topic when the input has it, "
                   "else the only sensor_msgs/Imu topic)")
    p.add_argument("--realtime", action="store_true", help="feed the input at its recorded rate into the node's "
                   "latest-wins worker: what the node would publish on this machine, clips the busy worker drops "
                   "included (default: every clip, in order, as fast as possible)")
    p.add_argument("--backbone-delay", type=float, metavar="S", help="add S seconds to every clip's processing, to "
                   "emulate a slower model (parameter backbone_delay)")
    p.add_argument("--force", action="store_true", help="replace an existing OUT (an MCAP file or rosbag2 folder); "
                   "never an input, nor an output another run is writing")
    p.add_argument("--copy-inputs", action="store_true", help="also write the input images and IMU")
    p.add_argument("--px4", action="store_true", help="also write the px4_msgs/VehicleOdometry that the node would "
                   "send PX4 (parameter px4_odom; no px4_msgs needed: its definition goes into the MCAP)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=run)


def settings_from_args(args: argparse.Namespace):
    """The replay's ``Settings``: defaults < --params-file < --param < the named options, checked once."""
    from vi3_ros.params import settings_from_cli  # the options' modules import torch

    return settings_from_cli(args.params_file, args.param, {
        "backbone": args.backbone, "mode": args.mode, "calib_file": args.calib, "device": args.device,
        "backbone_delay": args.backbone_delay, "px4_odom": True if args.px4 else None})


def run(args: argparse.Namespace) -> int:
    """Exit status: 0 with a complete output; 1 when no clip produced a result (the statuses saying why are kept as
    OUT.partial.mcap); 2 for an input, output or configuration that cannot be used; 128 + signal number (130 SIGINT,
    143 SIGTERM) when a signal arrived, at any moment. Every unfinished replay says on stderr what it kept."""
    with interrupts.trapped() as trap:  # first: a signal while torch or the backbone loads interrupts too
        try:
            from vi3_core.eval.report import to_json
            from vi3_ros.replay import kept_text, replay

            summary = replay(args.input, args.output, settings=settings_from_args(args), copy_inputs=args.copy_inputs,
                             progress=not args.no_progress and sys.stderr.isatty(), force=args.force,
                             image_topic=args.image_topic, imu_topic=args.imu_topic, realtime=args.realtime,
                             on_note=lambda note: print(f"vi3 replay: {note}", file=sys.stderr))
        except KeyboardInterrupt as exc:  # a ReplayInterrupted says what was kept; before the replay, nothing
            return _interrupted(trap, str(exc) or "nothing was written")
        except Vi3Error as exc:
            print(f"vi3 replay: {exc}", file=sys.stderr)
            return _interrupted(trap, "the replay had failed (above)") if trap.signum is not None else 2
        # The replay holds signals from its last step on (the output is final): one that came is reported below.
        print(to_json(summary.as_dict()) if args.json else f"wrote {summary.output}\n{summary.text()}")
        if trap.signum is not None:
            return _interrupted(trap, f"after the replay finished: {summary.output} is complete"
                                if summary.results or summary.odom_only
                                else f"after the replay finished without a result; {kept_text(summary.output)}")
        if not summary.results and summary.odom_only:
            print(f"vi3 replay: no clip claimed a scale (outcomes {dict(summary.outcomes)}); {summary.odom_only} were "
                  "placed in ~/odom at the window's scale (odom_max_scale_sigma)", file=sys.stderr)
        elif not summary.results:
            print(f"vi3 replay: no clip produced a result: {summary.why_nothing()}; "
                  f"{kept_text(summary.output)}", file=sys.stderr)
            return 1
        return 0


def _interrupted(trap: interrupts.Trap, kept: str) -> int:
    print(f"vi3 replay: interrupted by {trap.name}; {kept}", file=sys.stderr)
    return trap.status
