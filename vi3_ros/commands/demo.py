"""``vi3 demo``: the README's demo. On the bundled bag, with the embedded ``classical`` backbone: replay (writes
the output MCAP the node would publish), then evaluation against ground truth (prints the paper-like table, writes
the plot, the JSON report and TUM trajectories), then says where everything is and how to open the MCAP in its views
(RViz2's config and Foxglove's layout in config/).

Kept small so that ``make demo`` finishes in under 5 minutes on a 2-core CPU from a fresh clone: the bundled
short sequence, ``init`` mode for replay and evaluation, the paper's three clips; ``--ttr-steps K`` adds a short TTR
evaluated beside the fast init.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
#: The bundled sequence: a rosbag2 MCAP directory with its Kalibr calibration inside (see bags/README.md).
BUNDLED = REPO / "bags" / "vi3_demo"
#: The views of the output (installed by colcon in share/vi3_ros/config): RViz2's config and Foxglove's layout.
VIEWS = (REPO / "config" / "vi3.rviz", REPO / "config" / "vi3_foxglove.json")
#: What the demo's replay adds for the views: the input images and IMU, poses and points in odom (one 3D scene with
#: the path and the odometry) and the odom TF.
VIEW_ARGS = ("--copy-inputs", "--param", "outputs_in_odom=true", "--param", "publish_odom_tf=true")


def demo_inputs(source: Path) -> tuple[Path, Path, Path | None]:
    """(replay input, evaluation input, calibration YAML or None). Any input is used as is, except a
    ``vi3 make-bag OUT`` folder (``mcap/``, ``asl/``, ``camchain-imucam.yaml``): its rosbag2 MCAP and Kalibr
    camchain (bags carry no CameraInfo) for replay, and its ASL twin for evaluation (the bag has no GT depth; the
    ASL folder has, so every metric is defined)."""
    bundle = source
    if not (bundle / "mcap").is_dir():
        return source, source, None
    calib = bundle / "camchain-imucam.yaml"
    return (bundle / "mcap", bundle / "asl" if (bundle / "asl").is_dir() else bundle / "mcap",
            calib if calib.is_file() else None)


def replay_args(bag: Path, mcap: Path, *, backbone: str, calib: Path | None) -> list[str]:
    """The demo's ``vi3 replay`` command line: ``bag`` into ``mcap`` with ``backbone`` in init mode, with the views'
    additions (VIEW_ARGS)."""
    calib_args = ["--calib", str(calib)] if calib is not None else []
    return ["replay", str(bag), "--output", str(mcap), "--backbone", backbone, "--mode", "init", *calib_args,
            *VIEW_ARGS]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="run replay and evaluation on the bundled bag",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--input", default=str(BUNDLED),
                   help="a `vi3 make-bag` folder or any input `vi3 replay`/`vi3 eval` read (default: the bundled bag)")
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--backbone", default="classical", help="backbone (default: the embedded 'classical')")
    p.add_argument("--ttr-steps", type=int, default=0,
                   help="also run and evaluate a short TTR of this many steps after the fast init (default 0: init "
                        "only; each clip then costs tens of seconds more on a 2-core CPU)")
    p.set_defaults(func=run)


def _step(title: str) -> float:
    print(f"\n== {title}", flush=True)
    return time.perf_counter()


def run(args: argparse.Namespace) -> int:
    from vi3_ros import cli  # the demo drives the public subcommands, exactly as a user would

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    mcap, png, report_json, tum_dir = out / "vi3_output.mcap", out / "eval.png", out / "eval.json", out / "tum"
    source = Path(args.input)
    if not source.exists():
        print(f"vi3 demo: error: input {source} not found (the bundled bag lives in bags/ of the repository; "
              "pass --input to use another sequence)")
        return 2
    bag, eval_input, calib = demo_inputs(source)
    t_all = time.perf_counter()

    t0 = _step(f"1/2 replay {bag} -> {mcap}  (backbone {args.backbone}, init mode)")
    if mcap.exists():  # the demo's own output from an earlier run
        mcap.unlink()
    rc = cli.main(replay_args(bag, mcap, backbone=args.backbone, calib=calib))
    if rc:
        print(f"vi3 demo: replay failed with exit status {rc}")
        return rc
    print(f"   replay took {time.perf_counter() - t0:.1f} s")

    mode = ["--mode", "ttr", "--param", f"ttr_steps={args.ttr_steps}"] if args.ttr_steps > 0 else ["--mode", "init"]
    t0 = _step(f"2/2 evaluate {eval_input} against ground truth ({' '.join(mode)}, paper clips: start/middle/end)")
    rc = cli.main(["eval", str(eval_input), "--backbone", args.backbone, *mode, "--clips", "paper", "--plot", str(png),
                   "--json-out", str(report_json), "--export-tum", str(tum_dir)])
    if rc:
        print(f"vi3 demo: evaluation failed with exit status {rc}")
        return rc
    print(f"   evaluation took {time.perf_counter() - t0:.1f} s")
    if json.loads(report_json.read_text())["vi3"]["absrel"] is None:
        print("   (no GT depth in this input, so the depth metrics are --; `vi3 make-bag OUT` writes an ASL twin with "
              "GT depth, and `vi3 demo --input OUT` evaluates that one)")

    print(f"""
== done in {time.perf_counter() - t_all:.0f} s. Outputs in {out}/:
   {mcap}   what the node publishes (poses, depth 32FC1, PointCloud2, odometry, path, TF, status) and the
                             input images and IMU, rosbag2 MCAP
   {png}          top-down trajectories (GT black, base red, IMU blue, VI3 green) and point cloud
   {png.with_name(png.stem + "_sigma.png")}    each claimed clip's scale error against its scale sigma
   {report_json}         the metrics as JSON (schema: docs/evaluation.md)
   {tum_dir}/               TUM trajectories for evo, e.g. evo_traj tum {tum_dir}/clip000_*.txt -p

   Views (images, depth, point cloud, poses, odometry and path):
     Foxglove (https://app.foxglove.dev or the desktop app): Open local file -> {mcap}, then
       Layouts -> Import from file -> {VIEWS[1]}
     RViz2, on a ROS 2 Jazzy machine:
       ros2 bag play {mcap} --loop   and beside it   rviz2 -d {VIEWS[0]}
     Live: ros2 launch vi3_ros vi3.launch.py rviz:=true  (or views:=true with foxglove_bridge and the layout)""")
    return 0
