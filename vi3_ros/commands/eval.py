"""``vi3 eval INPUT [INPUT ...]``: the paper's metrics on sequences with ground truth (ASL folder, ROS 1 bag,
rosbag2, .mcap).

Prints paper-like tables (Base / IMU-init / IMU-cond / TTR columns) or, with ``--json``, one JSON object; writes
the top-down trajectory / point-cloud plot (``--plot``) and TUM trajectories for ``evo`` (``--export-tum``). With
several inputs every sequence is reported, then the clips of all of them pooled (the paper's medians over clips);
the JSON object is then {"sequences": [...], "pooled": {...}} and plots / TUM files get the sequence name.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

MODES = ("init", "cond", "ttr")  # = vi3_core.anchor.MODES, not imported here: that pulls in torch


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("eval", help="evaluate VI3 against ground truth (paper metrics, tables, plot)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("input", nargs="+",
                   help="ASL folder (mav0/ or its parent), ROS 1 .bag, rosbag2 folder or .mcap with GT; several: "
                        "each reported, then pooled")
    p.add_argument("--calib", default=None, metavar="YAML",
                   help="camera calibration (EuRoC sensor.yaml or Kalibr camchain) for bags that carry none")
    p.add_argument("--image-topic", default=None, help="camera topic of a bag (sensor_msgs/Image or CompressedImage; "
                   "default: /cam0/image_raw, else the only image topic)")
    p.add_argument("--imu-topic", default=None, help="IMU topic of a bag (default: /imu0, else the only "
                   "sensor_msgs/Imu topic)")
    p.add_argument("--backbone", default="classical", help="3DFM backbone (default: the embedded 'classical')")
    p.add_argument("--checkpoint", default=None, help="backbone checkpoint path (real 3DFMs)")
    p.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda")
    p.add_argument("--mode", choices=MODES, default="init",
                   help="anchoring mode of the VI3 column; cond/ttr also report the fast init (default: init)")
    p.add_argument("--init", choices=("vi3", "gt"), default="vi3", dest="init_source",
                   help="vi3: GT-free initialisation (default); gt: oracle init from ground truth")
    p.add_argument("--clips", choices=("paper", "sliding"), default="paper",
                   help="paper: start/middle/end clips (default); sliding: every --hop frames")
    p.add_argument("--n", type=int, default=8, help="frames per clip (default 8)")
    p.add_argument("--stride", type=int, default=2, help="frame stride within a clip (default 2)")
    p.add_argument("--hop", type=int, default=None, help="frames between sliding clips (default n*stride)")
    p.add_argument("--max-clips", type=_positive, default=None,
                   help="evaluate at most this many clips (evenly spread; >= 1)")
    p.add_argument("--steps", type=int, default=None, help="TTR steps (default: the paper's 160)")
    p.add_argument("--ablate", action="store_true",
                   help="initialisation ablations: TLS vs OLS, all-pairs vs first-pair v1, gravity consensus on/off "
                        "(each variant in init mode with the GT-free init; --mode and --init are ignored)")
    p.add_argument("--independent", action="store_true",
                   help="every clip on its own, as in the paper (default: the metric state is carried across clips "
                        "and the clips are chained into one odom trajectory; always independent with --init gt)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of tables")
    p.add_argument("--json-out", default=None, metavar="FILE", help="also write the JSON object to FILE")
    p.add_argument("--plot", default=None, metavar="PNG", help="write the trajectory / point-cloud plot here")
    p.add_argument("--export-tum", default=None, metavar="DIR",
                   help="write TUM trajectories (for evo) here: per clip, and the chained odom_vi3.txt / odom_gt.txt")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def run(args: argparse.Namespace) -> int:
    # Imported here, not at module level: they pull in torch, and `vi3 --help` should stay fast.
    from vi3_core.anchor import AnchorOptions
    from vi3_core.backbones import make_backbone
    from vi3_core.errors import Vi3Error
    from vi3_core.eval import report, runner

    try:
        backbone = make_backbone(args.backbone, device=args.device, checkpoint=args.checkpoint)
        options = runner.EvalOptions(
            mode=args.mode, init_source=args.init_source, clips=args.clips, n=args.n, stride=args.stride,
            hop=args.hop, max_clips=args.max_clips, progress=not args.no_progress,
            anchor_options=AnchorOptions(steps=args.steps) if args.steps is not None else None)
        results = [_evaluate(args, path, backbone, options, several=len(args.input) > 1) for path in args.input]
        if len(results) == 1:
            obj, text = results[0][:2]
        else:
            obj, text = {"sequences": [r[0] for r in results]}, "\n\n".join(r[1] for r in results)
            if not args.ablate:
                evals = [e for r in results for e in r[2]]
                pooled = report.summarise(evals, mode=args.mode, init_source=args.init_source,
                                          backbone=args.backbone, sequence=f"pooled ({len(results)} sequences)")
                text += "\n\n" + report.format_tables(pooled)
                runs = [r[3] for r in results if r[3] is not None]
                if runs:
                    pooled["chained"] = report.pool_chained(runs)
                    text += "\n" + report.format_pooled_chained(pooled["chained"])
                obj["pooled"] = pooled
        print(report.to_json(obj) if args.json else text)
        if args.json_out:
            Path(args.json_out).parent.mkdir(parents=True, exist_ok=True)
            Path(args.json_out).write_text(report.to_json(obj) + "\n")
    except (Vi3Error, ValueError, OSError) as exc:
        print(f"vi3 eval: error: {exc}", file=sys.stderr)
        return 2
    return 0


def _evaluate(args: argparse.Namespace, path: str, backbone, options, *, several: bool) -> tuple:
    """One input: (JSON object, text, evals, OnlineRun or None); writes its plot and TUM files (named after the
    sequence when there are several inputs)."""
    from vi3_core.eval import plot, report, runner, tum
    from vi3_ros.io.reader import open_sequence

    seq = open_sequence(path, calib=args.calib, image_topic=args.image_topic, imu_topic=args.imu_topic)
    meta = {"backbone": args.backbone, "sequence": seq.name}
    online = None
    if args.ablate:
        variants = runner.ablate(seq, backbone, options=options)
        summaries = {name: report.summarise(evals, mode="init", **meta) for name, evals in variants.items()}
        obj, text = {"sequence": seq.name, "ablations": summaries}, report.format_ablation(summaries)
        evals = next(iter(variants.values()))
    elif args.independent or args.init_source == "gt":
        evals = runner.evaluate_sequence(seq, backbone, options=options)
        obj = report.summarise(evals, mode=args.mode, init_source=args.init_source, **meta)
        text = report.format_tables(obj)
    else:
        evals, online = runner.evaluate_online(seq, backbone, options=options)
        obj = report.summarise(evals, mode=args.mode, init_source=args.init_source, **meta)
        obj["chained"] = report.chained_summary(online)
        text = report.format_tables(obj) + "\n" + report.format_chained(obj["chained"])
    if args.plot:
        png = Path(args.plot)
        png = png.with_name(f"{png.stem}_{seq.name}{png.suffix}") if several else png
        print(f"plot: {plot.save_plot(png, evals, title=f'{seq.name}: {args.backbone}, {args.mode}')}",
              file=sys.stderr)
    if args.export_tum:
        out = Path(args.export_tum) / seq.name if several else Path(args.export_tum)
        paths = tum.export_tum(out, evals) + (tum.export_chained(out, online) if online is not None else [])
        print(f"TUM trajectories: {len(paths)} files in {out}", file=sys.stderr)
    return obj, text, evals, online
