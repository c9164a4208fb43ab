"""One declaration of every parameter of the node and the replay tool: name, default (whose Python type is the
parameter's type), description, and range or choices.

The node declares each as a ROS parameter with a ``ParameterDescriptor`` built from this table; replay fills the
same values from ``--param NAME=VALUE`` and from a ROS 2 parameter YAML (``config/euroc.yaml``); ``docs/node.md``'s
table is ``markdown_table()``'s output.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from vi3_core.errors import DataError

NODE_NAME = "vi3_node"


@dataclass(frozen=True)
class Param:
    """name: ROS parameter name; default: its value and type (bool, int, float, str); range: inclusive (lo, hi)
    for numbers; choices: allowed strings."""

    name: str
    default: bool | int | float | str
    description: str
    range: tuple[float, float] | None = None
    choices: tuple[str, ...] = ()

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


PARAMS: tuple[Param, ...] = (
    # inputs
    Param("image_topic", "/cam0/image_raw", "camera images (sensor_msgs/Image, mono8/rgb8/bgr8...)"),
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
    Param("path_max_poses", 5000, "~/path keeps at most this many latest poses", range=(1, 1_000_000)),
    Param("online_max_gap", 1.0, "s; a longer gap between clips resets the online state (GT-free initialisation)",
          range=(0.01, 3600.0)),
    Param("online_gravity_tol", 30.0, "deg; the gravity prior is dropped for a clip when it is farther than this from "
          "the clip's own estimate (or fits the positions clearly worse, see online_residual_ratio)",
          range=(0.1, 180.0)),
    Param("online_residual_ratio", 4.0, "a prior (gravity, velocity) is dropped when the position residual with it "
          "exceeds this times the residual without it (and online_residual_floor)", range=(1.0, 1000.0)),
    Param("online_residual_floor", 0.03, "m; position residual always tolerated for a prior",
          range=(0.0, 100.0)),
    Param("online_scale_ratio", 2.0, "the velocity prior is dropped when the scale it implies differs from the "
          "clip's free position fit by more than this factor", range=(1.01, 100.0)),
    Param("online_bg_gain", 0.2, "weight of each clip's own gyro-bias estimate in the filtered bias",
          range=(0.0, 1.0)),
    Param("online_gravity_gain", 0.1, "weight of each clip's own gravity estimate when it refines the gravity prior",
          range=(0.0, 1.0)),
    Param("online_velocity_weight", 0.05, "s; weight of the velocity prior against the positions in the scale fit",
          range=(0.0, 1000.0)),
    # clip buffer
    Param("clip_length", 8, "frames per clip (n)", range=(2, 64)),
    Param("stride", 2, "use every stride-th input frame", range=(1, 100)),
    Param("hop", 0, "input frames between clip starts; 0: clip_length * stride (non-overlapping)", range=(0, 10000)),
    Param("max_frame_gap", 0.0, "s; a larger gap between consecutive frames restarts the clip; 0: automatic "
          "(1.5 x the median recent frame interval, so one dropped frame restarts)", range=(0.0, 60.0)),
    Param("time_offset", 0.0, "s; camera-IMU time offset, t_imu = t_cam + time_offset (Kalibr timeshift_cam_imu)",
          range=(-1.0, 1.0)),
    Param("imu_buffer", 4000, "IMU samples kept (bounded buffer)", range=(16, 1_000_000)),
    Param("imu_timeout", 0.5, "s of camera time a complete clip waits for IMU before it is dropped (imu_stalled)",
          range=(0.001, 60.0)),
    Param("imu_history", 0.0, "s of IMU before the clip kept for the long-window gravity seed; 0: none",
          range=(0.0, 60.0)),
    Param("max_pending", 4, "complete clips waiting for IMU before the oldest is dropped", range=(1, 1000)),
    # model and anchoring
    Param("backbone", "classical", "3D foundation model", choices=("classical", "vggt", "vggt_omega", "pi3", "pi3x",
                                                                    "da3")),
    Param("device", "cpu", "torch device of the backbone (cpu, cuda, cuda:1...)"),
    Param("checkpoint", "", "local checkpoint path or Hugging Face id; empty: the backbone's default"),
    Param("mode", "init", "refinement after the fast init result: init (none), cond (IMU-conditioned), ttr "
          "(test-time refinement)", choices=("init", "cond", "ttr")),
    Param("ttr_steps", 160, "TTR optimisation steps", range=(1, 100000)),
    Param("min_accel_rms", 0.15, "m/s^2; below it scale is unobservable and the clip is flagged", range=(0.0, 100.0)),
    Param("max_imu_gap", 0.05, "s; a larger gap between IMU samples inside a clip rejects it", range=(0.0, 10.0)),
    # outputs
    Param("depth_frames", "last", "~/depth for every clip frame (all) or only the last", choices=("last", "all")),
    Param("points_frames", "last", "~/points from every clip frame (all) or only the last", choices=("last", "all")),
    Param("points_stride", 2, "~/points keeps every k-th depth pixel in each direction", range=(1, 64)),
    Param("points_conf_quantile", 0.3, "~/points drops pixels whose confidence is below this quantile of the "
          "clip's confidences (backbone-independent; 0 keeps all)", range=(0.0, 0.99)),
    Param("points_max_depth", 20.0, "m; ~/points drops pixels farther than this", range=(0.1, 1000.0)),
    Param("diagnostics_period", 1.0, "s between /diagnostics summaries (node only)", range=(0.05, 3600.0)),
)

BY_NAME: dict[str, Param] = {p.name: p for p in PARAMS}


def defaults() -> dict[str, Any]:
    """Every parameter at its default."""
    return {p.name: p.default for p in PARAMS}


def resolve(overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """Defaults updated with checked ``overrides``; an unknown name is a DataError naming it."""
    values = defaults()
    for name, value in (overrides or {}).items():
        if name not in BY_NAME:
            raise DataError(f"unknown parameter {name!r} (known: {', '.join(BY_NAME)})")
        values[name] = BY_NAME[name].check(value)
    return values


def load_yaml(path: str | Path, *, node: str = NODE_NAME) -> dict[str, Any]:
    """The ``ros__parameters`` of ``node`` (or of ``/**``) in a ROS 2 parameter file, checked."""
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise DataError(f"cannot read parameter file {path}: {exc}") from exc
    for key in (node, f"/{node}", "/**"):
        section = (doc or {}).get(key) if isinstance(doc, dict) else None
        if isinstance(section, dict) and isinstance(section.get("ros__parameters"), dict):
            return {k: BY_NAME[k].check(v) if k in BY_NAME else _unknown(path, k)
                    for k, v in section["ros__parameters"].items()}
    raise DataError(f"{path}: no '{node}: ros__parameters:' (or '/**') section")


def _unknown(path: Path, name: str):
    raise DataError(f"{path}: unknown parameter {name!r}")


def parse_assignment(text: str) -> tuple[str, Any]:
    """``"NAME=VALUE"`` (from the command line) -> (name, checked value)."""
    name, sep, value = text.partition("=")
    if not sep or name not in BY_NAME:
        raise DataError(f"--param {text!r}: expected NAME=VALUE with NAME one of {', '.join(BY_NAME)}")
    return name, BY_NAME[name].check(value)


def markdown_table() -> str:
    """The parameter table of docs/node.md."""
    rows = ["| name | type | default | range / choices | description |", "|---|---|---|---|---|"]
    for p in PARAMS:
        allowed = " \\| ".join(p.choices) if p.choices else (f"[{p.range[0]}, {p.range[1]}]" if p.range else "")
        default = f'"{p.default}"' if isinstance(p.default, str) else str(p.default).lower() \
            if isinstance(p.default, bool) else str(p.default)
        rows.append(f"| `{p.name}` | {p.type.__name__} | {default} | {allowed} | {p.description} |")
    return "\n".join(rows)
