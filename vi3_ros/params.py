"""One declaration of every parameter of the node and the replay tool: name, default (whose Python type is the
parameter's type), description, and range or choices.

Parameters that set a field of an options dataclass (``ClipBufferOptions``, ``OnlineOptions``, ``InitOptions``,
``AnchorOptions``) take their default from that field, and ``options(cls, values)`` builds the dataclass from
parameter values, so the dataclass stays the one source of each default. Choices of ``backbone`` and ``mode`` are
the backbone registry's and the anchoring modes.

The node declares each as a ROS parameter with a ``ParameterDescriptor`` built from this table; replay fills the
same values from ``--param NAME=VALUE`` and from a ROS 2 parameter YAML (``config/euroc.yaml``); ``resolve`` is the
one place where values are checked; ``docs/node.md``'s table is ``markdown_table()``'s output.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import yaml

from vi3_core.anchor.options import MODES, AnchorOptions
from vi3_core.backbones import BACKBONES
from vi3_core.errors import DataError
from vi3_core.init.options import SCALE_SOLVERS, InitOptions
from vi3_core.online.options import OnlineOptions
from vi3_ros.clip_buffer import ClipBufferOptions

NODE_NAME = "vi3_node"
Options = TypeVar("Options")


@dataclass(frozen=True)
class Param:
    """name: ROS parameter name; default: its value and type (bool, int, float, str); range: inclusive (lo, hi)
    for numbers; choices: allowed strings; option: (options dataclass, field) that the value sets; none_as: the
    parameter value that stands for the field's None (e.g. ``hop`` 0)."""

    name: str
    default: bool | int | float | str
    description: str
    range: tuple[float, float] | None = None
    choices: tuple[str, ...] = ()
    option: tuple[type, str] | None = None
    none_as: bool | int | float | str | None = None

    @property
    def type(self) -> type:
        return type(self.default)

    def check(self, value: Any) -> bool | int | float | str:
        """``value`` converted to the parameter's type, or DataError naming the parameter and what is wrong."""
        t = self.type
        if t is bool:
            if isinstance(value, str) and value.lower() in ("true", "false"):
                value = value.lower() == "true"
            if not isinstance(value, bool):
                raise DataError(f"parameter {self.name}: expected true/false, got {value!r}")
        elif t in (int, float):
            try:
                if isinstance(value, bool) or (t is int and isinstance(value, float) and not value.is_integer()):
                    raise ValueError
                value = t(value)
            except (TypeError, ValueError):
                raise DataError(f"parameter {self.name}: expected {t.__name__}, got {value!r}") from None
            if self.range is not None and not self.range[0] <= value <= self.range[1]:
                raise DataError(f"parameter {self.name}: {value} is outside [{self.range[0]}, {self.range[1]}]")
        else:
            value = str(value)
            if self.choices and value not in self.choices:
                raise DataError(f"parameter {self.name}: {value!r} is not one of {', '.join(self.choices)}")
        return value


def _option(name: str, cls: type, field: str, description: str, *, range: tuple[float, float] | None = None,
            choices: tuple[str, ...] = (), none_as: bool | int | float | str | None = None) -> Param:
    """The parameter that sets ``cls.field``; its default is the field's default (``none_as`` where that is None)."""
    default = {f.name: f.default for f in dataclasses.fields(cls)}[field]
    return Param(name, none_as if default is None else default, description, range=range, choices=choices,
                 option=(cls, field), none_as=none_as)


PARAMS: tuple[Param, ...] = (
    # inputs
    Param("image_topic", "/cam0/image_raw", "camera images (sensor_msgs/Image, mono8/rgb8/bgr8..., or "
          "sensor_msgs/CompressedImage, JPEG/PNG: see image_transport)"),
    Param("image_transport", "auto", "message type on image_topic: raw (sensor_msgs/Image), compressed "
          "(sensor_msgs/CompressedImage), auto (node: the type its publishers have, learnt from the ROS graph; "
          "replay: the recording's)", choices=("auto", "raw", "compressed")),
    Param("imu_topic", "/imu0", "IMU samples (sensor_msgs/Imu)"),
    Param("camera_info_topic", "", "sensor_msgs/CameraInfo with the intrinsics; empty: use calib_file"),
    Param("calib_file", "", "EuRoC cam0/sensor.yaml or Kalibr camchain-imucam.yaml: intrinsics, distortion and "
          "T_BC (used for whatever camera_info_topic / tf_static do not provide)"),
    Param("use_tf_static", False, "take the camera pose in the IMU frame from /tf_static (imu_frame -> "
          "camera_frame) instead of calib_file"),
    # frames
    Param("clip_frame", "vi3_clip", "frame of ~/poses and ~/points: the clip's first camera (OpenCV optical axes)"),
    Param("camera_frame", "cam0", "optical frame of the camera (~/depth headers, TF child lookups)"),
    Param("imu_frame", "imu0", "IMU (body) frame, parent of camera_frame in /tf_static"),
    Param("publish_tf", False, "publish camera_frame -> clip_frame (the clip frame seen from the clip's last "
          "camera) so that the outputs hang off the live TF tree"),
    # online state across clips and the odom trajectory (vi3_core.online)
    Param("online", True, "carry the metric state (gravity, gyro bias, velocity) across clips as priors of each "
          "clip's initialisation, and chain the clips into one odom trajectory; false: every clip on its own (paper)"),
    Param("odom_frame", "odom", "frame of ~/odom and ~/path: continuous, gravity-aligned, z up (REP-105)"),
    Param("base_frame", "base_link", "child frame of ~/odom and of the odom TF: the IMU (body) frame"),
    Param("publish_odom_tf", False, "publish odom_frame -> base_frame on /tf at each clip's last frame (online only)"),
    Param("outputs_in_odom", False, "express ~/poses and ~/points in odom_frame instead of clip_frame (online only; "
          "a clip that is not chained keeps clip_frame)"),
    Param("imu_odom_rate", 200.0, "Hz; ~/odom/imu: the last chained state propagated with every IMU sample, published "
          "at most this often (every sample at the IMU's rate or above); 0: off (online only)", range=(0.0, 10000.0)),
    Param("imu_odom_max_sigma", 1.0, "m; ~/odom/imu stops, until the next chained clip, once its horizontal position "
          "1-sigma since the last chained frame exceeds this (a dead-reckoned pose a flight stack should not use); 0: "
          "no limit", range=(0.0, 1e6)),
    Param("path_max_poses", 5000, "~/path keeps at most this many latest poses", range=(1, 1_000_000)),
    _option("online_window", OnlineOptions, "window_s", "s; clips starting within this of the newest are fitted "
            "jointly (gravity and biases shared, velocities tied through the IMU, one scale per clip); older ones are "
            "marginalised into a prior", range=(0.5, 60.0)),
    _option("online_max_clips", OnlineOptions, "max_clips", "at most this many clips in the window", range=(1, 100)),
    _option("online_max_bridge", OnlineOptions, "max_bridge_s", "s; the longest gap between clips the IMU bridges "
            "(clips a busy worker dropped); longer, or IMU missing: the window restarts", range=(0.1, 3600.0)),
    _option("online_max_bridge_sigma", OnlineOptions, "max_bridge_sigma_m", "m; a clip placed through a bridge whose "
            "position 1-sigma exceeds this starts a new odom segment", range=(0.001, 1000.0)),
    _option("online_consistency_p", OnlineOptions, "consistency_p", "a clip whose residual in the window has a "
            "chi-square tail probability below this is inconsistent (rejected)", range=(1e-12, 0.5)),
    _option("online_max_rejects", OnlineOptions, "max_rejects", "inconsistent clips in a row that restart the "
            "window", range=(1, 1000)),
    _option("online_bg_window", OnlineOptions, "bg_window_s", "s; the gyro-bias prior is the median of the clips' "
            "own estimates over this long", range=(0.1, 3600.0)),
    # clip buffer
    _option("clip_length", ClipBufferOptions, "n", "frames per clip (n)", range=(2, 64)),
    _option("stride", ClipBufferOptions, "stride", "use every stride-th input frame", range=(1, 100)),
    _option("hop", ClipBufferOptions, "hop", "input frames between clip starts; 0: clip_length * stride "
            "(non-overlapping)", range=(0, 10000), none_as=0),
    _option("max_frame_gap", ClipBufferOptions, "max_frame_gap", "s; a larger gap between consecutive frames "
            "restarts the clip; 0: automatic (1.5 x the median recent frame interval, so one dropped frame restarts)",
            range=(0.0, 60.0)),
    _option("time_offset", ClipBufferOptions, "time_offset", "s; camera-IMU time offset, t_imu = t_cam + "
            "time_offset (Kalibr timeshift_cam_imu)", range=(-1.0, 1.0)),
    _option("imu_buffer", ClipBufferOptions, "imu_capacity", "IMU samples kept (bounded buffer)",
            range=(16, 1_000_000)),
    _option("imu_timeout", ClipBufferOptions, "imu_timeout", "s of camera time a complete clip waits for IMU before "
            "it is dropped (imu_stalled)", range=(0.001, 60.0)),
    _option("imu_history", ClipBufferOptions, "history", "s of IMU before the clip kept for the long-window gravity "
            "seed; 0: none", range=(0.0, 60.0)),
    _option("max_pending", ClipBufferOptions, "max_pending", "complete clips waiting for IMU before the oldest is "
            "dropped", range=(1, 1000)),
    # model and anchoring
    Param("backbone", "classical", "3D foundation model", choices=tuple(BACKBONES)),
    Param("device", "cpu", "torch device of the backbone (cpu, cuda, cuda:1...)"),
    Param("checkpoint", "", "local checkpoint path or Hugging Face id; empty: the backbone's default"),
    Param("threads", 0, "torch intra-op threads of the process (backbone forward, cond/ttr steps) and the classical "
          "backbone's plane-sweep threads, set once at start; 0: min(2, CPUs this process may use)",
          range=(0, 1024)),
    Param("mode", "init", "refinement after the fast init result: init (none), cond (IMU-conditioned), ttr "
          "(test-time refinement)", choices=MODES),
    Param("backbone_delay", 0.0, "s added to every clip's processing before the backbone, to emulate a slower model "
          "(testing: what a busy worker drops, how the odometry chains across the gaps)", range=(0.0, 3600.0)),
    _option("ttr_steps", AnchorOptions, "steps", "TTR optimisation steps", range=(1, 100000)),
    _option("scale_solver", InitOptions, "scale_solver", "eiv: backbone positions regressed on the IMU with an error "
            "model, a scale sigma per clip; tls / ols: the paper's Eq. S (no error model; independent clips only)",
            choices=SCALE_SOLVERS),
    _option("max_scale_sigma", InitOptions, "max_scale_rel_sigma", "a scale whose relative 1-sigma exceeds this is "
            "not claimed (unobservable)", range=(0.001, 10.0)),
    _option("max_rotation_error", InitOptions, "max_rotation_deg", "deg; a clip whose backbone relative rotations "
            "disagree with the bias-corrected gyro by more is a backbone failure (rejected)", range=(0.01, 180.0)),
    _option("accel_noise_density", InitOptions, "accel_noise_density", "m/s^2/sqrt(Hz); accelerometer noise of the "
            "error model (EuRoC's datasheet x 10)", range=(0.0, 10.0)),
    _option("gyro_noise_density", InitOptions, "gyro_noise_density", "rad/s/sqrt(Hz); gyro noise of the error model "
            "(EuRoC's datasheet x 5)", range=(0.0, 10.0)),
    _option("gyro_scale_error", InitOptions, "gyro_scale_error", "relative error of the integrated rotation in the "
            "error model", range=(0.0, 1.0)),
    _option("accel_bias_sigma", InitOptions, "accel_bias_sigma", "m/s^2; prior 1-sigma of the accelerometer bias",
            range=(1e-6, 10.0)),
    _option("accel_bias_walk", InitOptions, "accel_bias_walk", "m/s^2/sqrt(s); accelerometer bias random walk",
            range=(0.0, 10.0)),
    _option("gyro_bias_walk", InitOptions, "gyro_bias_walk", "rad/s/sqrt(s); gyro bias random walk",
            range=(0.0, 10.0)),
    _option("scale_rel_floor", InitOptions, "scale_rel_floor", "relative scale error the error model does not see "
            "(added to every sigma)", range=(0.0, 1.0)),
    _option("min_accel_rms", InitOptions, "min_accel_rms", "m/s^2; below it scale is unobservable and the clip is "
            "flagged", range=(0.0, 100.0)),
    _option("max_imu_gap", InitOptions, "max_imu_gap_s", "s; a larger gap between IMU samples inside a clip rejects "
            "it", range=(0.0, 10.0)),
    # outputs
    Param("depth_frames", "last", "~/depth for every clip frame (all) or only the last", choices=("last", "all")),
    Param("points_frames", "last", "~/points from every clip frame (all) or only the last", choices=("last", "all")),
    Param("points_stride", 2, "~/points keeps every k-th depth pixel in each direction", range=(1, 64)),
    Param("points_conf_quantile", 0.3, "~/points drops pixels whose confidence is below this quantile of the "
          "clip's confidences (backbone-independent; 0 keeps all)", range=(0.0, 0.99)),
    Param("points_max_depth", 20.0, "m; ~/points drops pixels farther than this", range=(0.1, 1000.0)),
    Param("diagnostics_period", 1.0, "s between /diagnostics summaries, which carry the dropped input messages "
          "counted by reason (node: timer; replay: bag time)", range=(0.05, 3600.0)),
)

BY_NAME: dict[str, Param] = {p.name: p for p in PARAMS}


def defaults() -> dict[str, Any]:
    """Every parameter at its default."""
    return {p.name: p.default for p in PARAMS}


def resolve(overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """Defaults updated with ``overrides``, each checked (``Param.check``); an unknown name is a DataError naming it."""
    values = defaults()
    for name, value in (overrides or {}).items():
        if name not in BY_NAME:
            raise DataError(f"unknown parameter {name!r} (known: {', '.join(BY_NAME)})")
        values[name] = BY_NAME[name].check(value)
    return values


def options(cls: type[Options], values: dict[str, Any], **fixed: Any) -> Options:
    """The options dataclass ``cls`` with every field a parameter sets taken from ``values`` (``resolve``'s output)
    and the fields in ``fixed``; other fields keep their defaults."""
    fields = {p.option[1]: None if p.none_as is not None and values[p.name] == p.none_as else values[p.name]
              for p in PARAMS if p.option is not None and p.option[0] is cls}
    return cls(**fields, **fixed)


def load_yaml(path: str | Path, *, node: str = NODE_NAME) -> dict[str, Any]:
    """The ``ros__parameters`` of ``node`` (or of ``/**``) in a ROS 2 parameter file, as written (names checked;
    ``resolve`` checks the values)."""
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise DataError(f"cannot read parameter file {path}: {exc}") from exc
    for key in (node, f"/{node}", "/**"):
        section = (doc or {}).get(key) if isinstance(doc, dict) else None
        if isinstance(section, dict) and isinstance(section.get("ros__parameters"), dict):
            params = section["ros__parameters"]
            unknown = [k for k in params if k not in BY_NAME]
            if unknown:
                raise DataError(f"{path}: unknown parameter {unknown[0]!r}")
            return dict(params)
    raise DataError(f"{path}: no '{node}: ros__parameters:' (or '/**') section")


def parse_assignment(text: str) -> tuple[str, str]:
    """``"NAME=VALUE"`` (from the command line) -> (name, value text); ``resolve`` checks and converts the value."""
    name, sep, value = text.partition("=")
    if not sep or name not in BY_NAME:
        raise DataError(f"--param {text!r}: expected NAME=VALUE with NAME one of {', '.join(BY_NAME)}")
    return name, value


def markdown_table() -> str:
    """The parameter table of docs/node.md."""
    rows = ["| name | type | default | range / choices | description |", "|---|---|---|---|---|"]
    for p in PARAMS:
        allowed = " \\| ".join(p.choices) if p.choices else (f"[{p.range[0]}, {p.range[1]}]" if p.range else "")
        default = f'"{p.default}"' if isinstance(p.default, str) else str(p.default).lower() \
            if isinstance(p.default, bool) else str(p.default)
        rows.append(f"| `{p.name}` | {p.type.__name__} | {default} | {allowed} | {p.description} |")
    return "\n".join(rows)
