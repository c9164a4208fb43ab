"""``vi3 eval INPUT [INPUT ...]``: the paper's metrics on sequences with ground truth (ASL folder, ROS 1 bag,
rosbag2, .mcap).

Prints a per-clip table and paper-like tables (Base / IMU-init / IMU-cond / TTR columns, paired over the same
clips) or, with ``--json``, one JSON object; writes the top-down trajectory / point-cloud plot and its scale-sigma
companion (``--plot``) and TUM trajectories for ``evo`` (``--export-tum``). With several inputs every sequence is
reported, then the clips of all of them pooled (the paper's medians over clips); the JSON object is then
{"sequences": [...], "pooled": {...}} and plots / TUM files get the sequence name (unique within the run).

Every input and output path is checked before any clip is evaluated (an output file that is an input, under any
name, is refused). A failure after that (a clip that cannot be read, an output that cannot be written) still writes
what was computed, marked ``"partial": true`` with the errors, and exits with status 2. Ctrl-C or SIGTERM stops the
run and writes what had finished the same way, marked partial, with exit status 130 / 143 (128 + the signal).

With ``--ray [ADDRESS]`` the clips (independent runs) or whole sequences (chained runs) are evaluated by a pool of
Ray workers (``vi3_core.eval.distributed``), each building the backbone once and reading the inputs from their path,
which every node must see; the report is the serial run's. A clip whose worker died is run again (twice at most);
Ctrl-C and SIGTERM stop the workers and write what had finished, as in a serial run.
"""

from __future__ import annotations

import argparse
import functools
import os
import re
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path

from vi3_ros import interrupts

MODES = ("init", "cond", "ttr")  # = vi3_core.anchor.MODES, not imported here: that pulls in torch
RESERVED_NAMES = ("sigma",)  # <stem>_sigma.png is the sigma plot's
RAY_ADDRESS = re.compile(r"auto|local|(ray://)?[\w.\-\[\]:]+:\d+")  # what ray.init(address=...) connects to


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
    p.add_argument("--reference", default=None, metavar="TUM",
                   help="ground truth for a recording that has none: a TUM trajectory (t tx ty tz qx qy qz qw per "
                        "line; s, m) of the IMU body in a gravity-aligned, z-up world, as a motion-capture system or "
                        "`vi3 reference` writes it (velocities from its positions, biases unknown), stamped on the "
                        "frames' clock; the frames it covers are evaluated; one input only")
    p.add_argument("--backbone", default="classical",
                   help="3DFM backbone (default: the embedded 'classical'); 'gt' is the ground-truth pose instrument "
                        "(see --gt-noise), an evaluation tool, never a backbone for the node")
    p.add_argument("--gt-noise", default=None, metavar="POS_M,ROT_DEG[,DRIFT_M]",
                   help="with --backbone gt: per-frame position (m) and rotation (deg) noise of the ground-truth "
                        "poses, and an optional random-walk position drift (m at the clip's last frame); default 0,0. "
                        "Works on recordings of IMU and ground truth without images")
    p.add_argument("--gt-depth-noise", default=None, metavar="REL[,SMOOTH]",
                   help="with --backbone gt on a recording with depth (generated or --from-euroc): each clip's depth "
                        "at its model scale times exp(REL N(0,1) per pixel + SMOOTH x a low-frequency field per frame, "
                        "a few cycles across the image); default 0 (exact depth)")
    p.add_argument("--gt-seed", type=int, default=0, metavar="N",
                   help="with --backbone gt: seed of the noise (each clip's noise is drawn from N and its first "
                        "stamp, so a run is repeatable); default 0")
    p.add_argument("--calib-error", default=None, metavar="RX_DEG,RY_DEG,RZ_DEG[,IMU_DELAY_MS]", type=_rig_error,
                   help="evaluate with a wrong rig calibration, as a user's own file may be: the camera mount the "
                        "estimator is given is the true one turned back by (RX, RY, RZ) deg about the body axes, and "
                        "the IMU stamps are IMU_DELAY_MS late (the images, the gt instrument and the ground truth "
                        "keep the truth); measures the self-calibration")
    p.add_argument("--checkpoint", default=None, help="backbone checkpoint path (real 3DFMs)")
    p.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda")
    p.add_argument("--mode", choices=MODES, default=None,
                   help="anchoring mode of the VI3 column (parameter mode); cond/ttr also report the fast init "
                        "(default: init)")
    p.add_argument("--init", choices=("vi3", "gt"), default="vi3", dest="init_source",
                   help="vi3: GT-free initialisation (default); gt: oracle init from ground truth")
    p.add_argument("--clips", choices=("paper", "sliding"), default=None,
                   help="paper: start/middle/end clips; sliding: every hop frames (parameter hop; default: sliding "
                        "when chaining, "
                        "paper with --independent, --init gt or --ablate)")
    p.add_argument("--max-clips", type=_positive, default=None,
                   help="evaluate at most this many clips (evenly spread; >= 1)")
    p.add_argument("--ablate", action="store_true",
                   help="initialisation ablations: TLS vs OLS, all-pairs vs first-pair v1, gravity consensus on/off "
                        "(each variant in init mode with the GT-free init; --mode and --init are ignored)")
    p.add_argument("--independent", action="store_true",
                   help="every clip on its own, as in the paper (parameter online false; default: the metric state is "
                        "carried across clips and the clips are chained into one odom trajectory; always independent "
                        "with --init gt)")
    p.add_argument("--params-file", default=None, metavar="YAML",
                   help="ROS 2 parameter YAML of the node (e.g. config/euroc.yaml): its clip, window, error-model and "
                        "TTR settings (clip_length, stride, hop, online_*, max_scale_sigma, ttr_steps, ...)")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="any node parameter, as in vi3 replay (e.g. max_scale_sigma=0.05, hop=8, ttr_steps=40); "
                        "overrides --params-file")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of tables")
    p.add_argument("--json-out", default=None, metavar="FILE", help="also write the JSON object to FILE")
    p.add_argument("--plot", default=None, metavar="PNG",
                   help="write the trajectory / point-cloud plot here, and the scale error against its sigma to "
                        "<stem>_sigma.png")
    p.add_argument("--export-tum", default=None, metavar="DIR",
                   help="write TUM trajectories (for evo) here: per clip, and the chained odom_vi3.txt / odom_gt.txt")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--ray", nargs="?", const="", default=None, metavar="ADDRESS", type=_ray_address,
                   help="evaluate on Ray workers: without ADDRESS on RAY_ADDRESS, a cluster started with `ray start` "
                        "here, or else a new local instance on this machine's cores; else on the cluster at ADDRESS "
                        "(auto, local, HEAD_HOST:6379 or "
                        "ray://HEAD_HOST:10001); every node must see the inputs at the same path. Put it after the "
                        "inputs (or write --ray=ADDRESS). Needs Ray: pip install '.[ray]' in a clone")
    p.add_argument("--ray-cpus-per-task", type=_non_negative, default=None, metavar="N",
                   help="CPUs each Ray worker reserves (default 1)")
    p.add_argument("--ray-gpus-per-task", type=_non_negative, default=None, metavar="N",
                   help="GPUs each Ray worker reserves, fractions allowed (default 0; --device cuda needs > 0)")
    p.set_defaults(func=run)


@dataclass
class Evaluated:
    """One input of the run: its unique ``name``, the opened sequence (kept only while it waits to be evaluated),
    the frame indices of its clips, its JSON object and text (once evaluated), the clip evaluations and the chained
    run (None when independent), the clip evaluations of each ablation variant (``--ablate``), and the ``error``
    that stopped it ("" when none)."""

    name: str
    path: str
    seq: object = None
    clips: list = field(default_factory=list)
    obj: dict = field(default_factory=dict)
    text: str = ""
    evals: list = field(default_factory=list)
    online: object = None
    variants: dict = field(default_factory=dict)
    error: str = ""


def _chained(args: argparse.Namespace) -> bool:
    return not (args.ablate or args.init_source == "gt") and args.settings.stream.online


def _open(args: argparse.Namespace, path: str):
    return _opener(args)(path)


def _opener(args: argparse.Namespace, *, absolute: bool = False) -> functools.partial:
    """A function that opens an input path with the run's calibration and topics (it pickles, for Ray workers;
    ``absolute``: with the calibration's absolute path, for workers in another folder)."""
    calib = os.path.abspath(args.calib) if absolute and args.calib else args.calib
    reference = os.path.abspath(args.reference) if absolute and args.reference else args.reference
    return functools.partial(_open_path, calib=calib, image_topic=args.image_topic, imu_topic=args.imu_topic,
                             calib_error=args.calib_error, reference=reference)


def _open_path(path: str, *, calib_error=None, reference: str | None = None, **kwargs):
    from vi3_core.eval.tum import reference_track
    from vi3_ros.io.reader import open_sequence

    seq = open_sequence(path, **kwargs)
    if reference:
        track = reference_track(reference)
        seq = seq.within(track.t[0], track.t[-1])
        seq.gt = track
    return calib_error.apply(seq) if calib_error is not None else seq


def unique_names(names: list[str], reserved: tuple[str, ...] = RESERVED_NAMES) -> list[str]:
    """``names`` made unique in order (a repeated name gets ``_2``, ``_3``, ...), none of them in ``reserved``."""
    taken, out = set(reserved), []
    for name in names:
        cand, k = name, 2
        while cand in taken:
            cand, k = f"{name}_{k}", k + 1
        taken.add(cand)
        out.append(cand)
    return out


def _check_dir(path: Path, what: str) -> None:
    """``path`` is, or can be created as, a writable folder (nothing is created)."""
    probe = path
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        raise OSError(f"{what} {path}: {probe} is not a folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise OSError(f"{what} {path}: {probe} is not writable")


def _check_file(path: Path, what: str) -> None:
    if path.is_dir():
        raise OSError(f"{what} {path}: is a folder")
    if path.exists() and not os.access(path, os.W_OK):
        raise OSError(f"{what} {path}: not writable")
    _check_dir(path.parent, what)


def check_outputs(args: argparse.Namespace) -> None:
    """Raise OSError when --plot, --json-out or --export-tum cannot be written (nothing is created)."""
    for value, what in ((args.plot, "--plot"), (args.json_out, "--json-out")):
        if value:
            _check_file(Path(value), what)
    if args.export_tum:
        _check_dir(Path(args.export_tum), "--export-tum")


def output_paths(args: argparse.Namespace, names: list[str]) -> dict:
    """Where each output of the run goes: {"plots": {name: png}, "sigma": png or None, "tum": {name: dir},
    "json": file or None}; raises OSError when one is not writable or two outputs would be the same path, DataError
    when one is an input."""
    from vi3_core.eval.plot import sigma_plot_path
    from vi3_core.paths import check_apart

    several = len(names) > 1
    plots, tum, sigma = {}, {}, None
    if args.plot:
        png = Path(args.plot)
        plots = {n: png.with_name(f"{png.stem}_{n}{png.suffix}") if several else png for n in names}
        sigma = sigma_plot_path(png)
    if args.export_tum:
        tum = {n: Path(args.export_tum) / n if several else Path(args.export_tum) for n in names}
    json_out = Path(args.json_out) if args.json_out else None
    files = [*plots.values(), *([sigma] if sigma else []), *([json_out] if json_out else [])]
    for f in files:
        _check_file(f, "--json-out" if f == json_out else "--plot")
    inputs = [*args.input, *([args.calib] if args.calib else [])]
    for f in files:  # written over; TUM files are written into their folder, the plots' neighbours untouched
        check_apart(f, inputs, what="--json-out" if f == json_out else "--plot", relations=("is",))
    resolved = [f.resolve() for f in files]
    dirs = {d.resolve() for d in tum.values()}
    clash = {str(f) for f in resolved if resolved.count(f) > 1 or f in dirs}
    if clash:
        raise OSError(f"two outputs of this run would be the same path: {', '.join(sorted(clash))}")
    return {"plots": plots, "sigma": sigma, "tum": tum, "json": json_out}


def _ray_address(text: str) -> str:
    """``--ray``'s ADDRESS, checked as it is parsed: an input right after ``--ray`` would otherwise be taken for it,
    and the inputs then said to be missing."""
    if text and not RAY_ADDRESS.fullmatch(text):  # "": --ray without ADDRESS
        raise argparse.ArgumentTypeError(f"{text!r} is not a Ray address (auto, local, HOST:PORT or ray://HOST:PORT); "
                                         "an input right after --ray is taken for its ADDRESS: put --ray after the "
                                         "inputs, or write --ray=ADDRESS")
    return text


def _rig_error(text: str):
    """``--calib-error``, parsed as it is read (``vi3_core.eval.perturb.RigError``)."""
    from vi3_core.eval.perturb import RigError

    try:
        return RigError.parse(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _non_negative(text: str) -> float:
    value = float(text)
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return value


def run(args: argparse.Namespace) -> int:
    """Exit status: 0 all written; 2 an input, output or option that cannot be used (nothing evaluated), or a
    failure part-way (what was computed is written, marked partial); 128 + the signal number when interrupted (what
    had finished is written, marked partial; nothing when no clip had finished)."""
    # Imported here, not at module level: they pull in torch, and `vi3 --help` should stay fast.
    from vi3_core.errors import Vi3Error
    from vi3_core.eval import runner

    with interrupts.trapped() as trap:
        try:
            options, backbone, runs, outputs = _prepare(args)
        except KeyboardInterrupt:
            print(f"vi3 eval: interrupted by {trap.name} before any clip was evaluated; nothing was "
                  "written", file=sys.stderr)
            return trap.status
        except (Vi3Error, ValueError, OSError) as exc:
            print(f"vi3 eval: error: {exc}", file=sys.stderr)
            return 2
        try:
            if args.ray is not None:
                _evaluate_ray(args, runs, options, backbone)
            else:
                for item in runs:
                    _evaluate(args, item, backbone, options)
        except KeyboardInterrupt:  # what had finished is written below, marked partial
            pass
        except (Vi3Error, ValueError, OSError) as exc:  # no Ray worker could start
            print(f"vi3 eval: error: {exc}", file=sys.stderr)
            return 2
        interrupts.hold()  # the outputs are written whole; a signal from here on is reported after them
        if trap.raised:
            for r in runs:
                if not (r.error or r.evals or r.variants):
                    r.error = runner.interrupted_note(0, len(r.clips))
        obj, text = _combine(args, runs)
        errors = [f"{r.name}: {r.error}" for r in runs if r.error] + _write_outputs(args, runs, outputs)
        if errors:
            obj["partial"], obj["errors"] = True, errors
            text += "\n\nPARTIAL: " + "; ".join(errors)
        try:
            _emit(args, obj, text, outputs["json"])
        except OSError as exc:
            errors.append(str(exc))
        for e in errors:
            print(f"vi3 eval: error: {e}", file=sys.stderr)
        if trap.signum is not None:
            kept = ("what had finished is written, marked partial" if trap.raised else
                    "after the evaluation finished: the outputs are complete")
            print(f"vi3 eval: interrupted by {trap.name}; {kept}", file=sys.stderr)
            return trap.status
        return 2 if errors else 0


def _backbone(args: argparse.Namespace):
    """A function that builds the backbone of ``--backbone``, or the ground-truth pose instrument for ``gt`` (it
    pickles, for Ray workers); the options are checked here."""
    from vi3_core.backbones import backbone_class, make_backbone

    if args.backbone == "gt":
        from vi3_core.backbones.ground_truth import GroundTruthPoses
        from vi3_core.sim.visual import DepthNoise, PoseNoise

        mount_error = args.calib_error.rotation if args.calib_error is not None else None
        return functools.partial(GroundTruthPoses, noise=PoseNoise.parse(args.gt_noise or "0,0"),
                                 depth_noise=DepthNoise.parse(args.gt_depth_noise or "0"), seed=args.gt_seed,
                                 mount_error=mount_error)
    if args.gt_noise is not None or args.gt_depth_noise is not None or args.gt_seed:
        raise ValueError("--gt-noise, --gt-depth-noise and --gt-seed need --backbone gt (the ground-truth pose "
                         "instrument)")
    backbone_class(args.backbone)  # a known name
    return functools.partial(make_backbone, args.backbone, device=args.device, checkpoint=args.checkpoint,
                             **args.settings.model.backbone_options(args.backbone))


def _prepare(args: argparse.Namespace) -> tuple:
    """Options, backbone (with --ray, the function that builds it on the workers), one ``Evaluated`` per input
    (opened and checked: GT, calibration, enough frames; the sequence itself kept only for a single input evaluated
    here) and the output paths, all checked before any clip runs."""
    from vi3_core.errors import DataError, Vi3Error
    from vi3_core.eval import runner
    from vi3_ros.params import settings_from_cli

    args.settings = settings = settings_from_cli(args.params_file, args.param, {
        "mode": args.mode, "online": False if args.independent else None})
    _check_ray_args(args)
    if args.reference and len(args.input) != 1:
        raise ValueError(f"--reference is the ground truth of one input; {len(args.input)} inputs were given")
    clips = args.clips or ("sliding" if _chained(args) else "paper")
    buf = settings.buffer
    stream = replace(settings.stream, online=False, init_source=args.init_source, all_depth=settings.outputs.all_depth)
    options = runner.EvalOptions(
        stream_options=stream, clips=clips, clip_length=buf.clip_length, stride=buf.stride, hop=buf.hop,
        max_clips=args.max_clips, progress=not args.no_progress, anchor_options=settings.anchor,
        init_options=settings.init, online_options=settings.online, calibration_options=settings.calibration)
    check_outputs(args)
    runs, problems = [], []
    keep = len(args.input) == 1 and args.ray is None
    for path in args.input:
        try:
            seq = _open(args, path)
            sampled = runner.check_sequence(seq, options=options, chained=_chained(args))
        except (Vi3Error, ValueError, OSError) as exc:
            problems.append(f"input {path}: {exc}")
            continue
        if args.backbone == "gt" and args.gt_depth_noise is not None and seq.depth_gt == "none":
            problems.append(f"input {path}: --gt-depth-noise needs depth ground truth (depth0/ of an ASL folder: "
                            "vi3 make-bag without --no-depth), and it has none")
            continue
        if seq.depth_gt.startswith("unreadable"):
            print(f"vi3 eval: {path}: depth ground truth {seq.depth_gt}; the depth metrics will be null",
                  file=sys.stderr)
        # Several inputs are reopened one at a time when evaluated (bags are read into memory whole); Ray workers
        # open their own.
        skipped = runner.skipped_clips(seq, options=options, chained=_chained(args))
        runs.append(Evaluated(seq.name, path, seq=seq if keep else None, clips=sampled,
                              obj={"input": path, "depth_gt": seq.depth_gt, "skipped_clips": [
                                  {"frames": [int(idx[0]), int(idx[-1])], "reason": runner.IMU_MISSING}
                                  for idx in skipped]}))
    if problems:
        raise DataError("; ".join(problems))
    for item, name in zip(runs, unique_names([r.name for r in runs])):
        item.name, item.obj = name, {"sequence": name, **item.obj}
    outputs = output_paths(args, [r.name for r in runs])
    backbone = _backbone(args)
    return options, backbone if args.ray is not None else backbone(), runs, outputs


def _evaluate(args: argparse.Namespace, item: Evaluated, backbone, options) -> None:
    """Evaluate one input into ``item``; a failure part-way keeps what was computed and names the error, and so does
    an interruption, which is raised on (``runner.EvaluationInterrupted``)."""
    from vi3_core.errors import Vi3Error
    from vi3_core.eval import runner

    seq, item.seq = item.seq, None
    try:
        seq = seq if seq is not None else _open(args, item.path)
        seq.name = item.name
        if args.ablate:
            item.variants = runner.ablate(seq, backbone, options=options)
        elif _chained(args):
            item.evals, item.online = runner.evaluate_online(seq, backbone, options=options)
        else:
            item.evals = runner.evaluate_sequence(seq, backbone, options=options)
    except runner.EvaluationStopped as exc:
        item.evals, item.online, item.error = exc.evals, exc.online, str(exc)
    except runner.EvaluationInterrupted as exc:
        item.evals, item.online = exc.evals, exc.online
        item.error = runner.interrupted_note(len(exc.evals), len(item.clips))
        if item.evals and not args.ablate:
            _report(args, item)
        raise
    except (Vi3Error, ValueError, OSError) as exc:
        item.error = str(exc)
        return
    if not (args.ablate and item.error):
        _report(args, item)


def _report(args: argparse.Namespace, item: Evaluated) -> None:
    """``item``'s JSON object and text from its clip evaluations (and chained run, or ablation variants)."""
    from vi3_core.eval import report

    meta = {"backbone": args.backbone, "sequence": item.name}
    if args.ablate:
        summaries = {name: report.summarise(evals, mode="init", **meta) for name, evals in item.variants.items()}
        item.obj |= {"ablations": summaries}
        item.text = report.format_ablation(summaries)
        item.evals = next(iter(item.variants.values()))
        return
    summary = report.summarise(item.evals, mode=args.settings.stream.mode, init_source=args.init_source, **meta)
    item.obj = {**item.obj, **summary, "input": item.path}
    if item.online is not None:
        item.obj["chained"] = report.chained_summary(item.online)
    item.text = "\n\n".join([report.format_clips(item.obj), report.format_tables(item.obj)]
                            + ([report.format_chained(item.obj["chained"], item.obj)] if item.online else []))


def _check_ray_args(args: argparse.Namespace) -> None:
    """ValueError for --ray-* options without --ray, or a CUDA device without a GPU per task (the ADDRESS is checked
    by ``_ray_address``); ClusterUnavailable, saying how to install it, when Ray is missing."""
    per_task = [f"--ray-{kind}-per-task" for kind, v in (("cpus", args.ray_cpus_per_task),
                                                         ("gpus", args.ray_gpus_per_task)) if v is not None]
    if args.ray is None:
        if per_task:
            raise ValueError(f"{' and '.join(per_task)} need --ray")
        return
    from vi3_core.eval.distributed import import_ray

    import_ray()
    if args.device.startswith("cuda") and not args.ray_gpus_per_task:
        raise ValueError(f"--device {args.device} with --ray needs --ray-gpus-per-task > 0 (Ray gives a worker only "
                         "the GPUs it reserves)")


def _evaluate_ray(args: argparse.Namespace, runs: list[Evaluated], options, backbone) -> None:
    """Evaluate every input on Ray workers (``vi3_core.eval.distributed``) into ``runs``, as ``_evaluate`` does one
    by one (a signal stops the workers: what had finished is kept, the rest named as interrupted). Raises
    ClusterUnavailable when no worker can start."""
    import dataclasses

    from tqdm import tqdm

    from vi3_core.eval import distributed, runner

    task_options = dataclasses.replace(options, progress=False)
    variants = runner.ablation_options(task_options) if args.ablate else {"": task_options}
    jobs = [distributed.Job(os.path.abspath(r.path), r.name, opts, tuple(r.clips), chained=_chained(args))
            for r in runs for opts in variants.values()]
    connected = distributed.connect(args.ray or None)
    interrupts.reinstall()  # ray.init replaces the SIGTERM handler with one that exits at once
    try:
        with tqdm(total=sum(len(j.clips) for j in jobs), unit="clip", desc="eval (ray)",
                  disable=not options.progress) as bar:
            ran = distributed.evaluate(
                jobs, backbone=backbone, open_sequence=_opener(args, absolute=True),
                cpus_per_task=1.0 if args.ray_cpus_per_task is None else args.ray_cpus_per_task,
                gpus_per_task=args.ray_gpus_per_task or 0.0,
                on_progress=lambda n: bar.update(n - bar.n),
                on_event=lambda line: bar.write(f"vi3 eval: {line}", file=sys.stderr))
    finally:
        if connected:
            import ray

            ray.shutdown()
    hosts = {w.split()[0] for w in ran.workers}
    print(f"vi3 eval: ray: {len(ran.workers)} workers on {len(hosts)} node(s), {len(ran.retried)} tasks run again",
          file=sys.stderr)
    results = iter(ran.results)
    for item in runs:
        parts = {name: next(results) for name in variants}
        item.error = "; ".join(e for p in parts.values() for e in p.errors)
        if args.ablate:
            item.variants = {name: p.evals for name, p in parts.items()}
        else:
            item.evals, item.online = parts[""].evals, parts[""].online
        if item.evals or item.online is not None or any(item.variants.values()):
            _report(args, item)


def _combine(args: argparse.Namespace, runs: list[Evaluated]) -> tuple[dict, str]:
    """The run's JSON object and text: the one sequence's, or every sequence's, an overview line per sequence and
    the pooled clips."""
    from vi3_core.eval import report

    for r in runs:
        if r.error:
            r.obj["error"] = r.error
    if len(runs) == 1:
        return runs[0].obj, runs[0].text or f"{runs[0].name}: {runs[0].error}"
    obj = {"sequences": [r.obj for r in runs]}
    text = "\n\n".join(r.text for r in runs if r.text)
    if not args.ablate:
        text += "\n\n" + report.format_overview(obj["sequences"])
        evals = [e for r in runs for e in r.evals]
        done = sum(bool(r.evals) for r in runs)
        pooled = report.summarise(evals, mode=args.settings.stream.mode, init_source=args.init_source,
                                  backbone=args.backbone,
                                  sequence=f"pooled ({done} of {len(runs)} sequences)")
        text += "\n\n" + report.format_tables(pooled)
        if _chained(args):
            pooled["chained"] = report.pool_chained([(r.name, r.online) for r in runs if r.online is not None])
            text += "\n" + report.format_pooled_chained(pooled["chained"])
        obj["pooled"] = pooled
    return obj, text


def _write_outputs(args: argparse.Namespace, runs: list[Evaluated], outputs: dict) -> list[str]:
    """Plots and TUM files of every evaluated sequence, then the sigma plot; the errors of those that failed."""
    from vi3_core.eval import claims, plot, report, tum

    errors = []
    for r in runs:
        if not r.evals:
            continue
        try:
            if r.name in outputs["plots"]:
                png = plot.save_plot(outputs["plots"][r.name], r.evals,
                                     title=f"{r.name}: {args.backbone}, {args.settings.stream.mode}")
                print(f"plot: {png}", file=sys.stderr)
            if r.name in outputs["tum"]:
                out = outputs["tum"][r.name]
                paths = tum.export_tum(out, r.evals) + (tum.export_chained(out, r.online) if r.online else [])
                print(f"TUM trajectories: {len(paths)} files in {out}", file=sys.stderr)
        except (OSError, ValueError) as exc:
            errors.append(f"{r.name}: output not written: {exc}")
    if outputs["sigma"] and not args.ablate:
        evaluated = [r for r in runs if r.evals]
        series = {"VI3" + (" (chained)" if _chained(args) else ""):
                  claims.Claims.concatenate(claims.clip_claims(r.evals, "init") for r in evaluated)}
        if _chained(args):
            series["own init"] = claims.Claims.concatenate(report.independent_claims(r.online) for r in evaluated
                                                           if r.online is not None)
        try:
            png = plot.save_sigma_plot(outputs["sigma"], series, title=f"{', '.join(r.name for r in evaluated)}: "
                                       "scale error against its sigma (claimed clips)")
            print(f"sigma plot: {png}", file=sys.stderr)
        except (OSError, ValueError) as exc:
            errors.append(f"sigma plot not written: {exc}")
    return errors


def _emit(args: argparse.Namespace, obj: dict, text: str, json_out: Path | None) -> None:
    from vi3_core.eval import report

    doc = report.to_json(obj)
    print(doc if args.json else text)
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(doc + "\n")
