"""One declaration of every parameter of the node and the replay tool: name, description, and range or choices.

Every parameter is a field of the same name in one options dataclass (``vi3_ros.settings``' groups, the clip buffer's,
and the core's ``StreamOptions``, ``OnlineOptions``, ``InitOptions``, ``AnchorOptions``), whose default is the
parameter's default and whose Python type is its type: one name per setting, in the ROS parameter table, in
``vi3 replay|eval|bench --param NAME=VALUE``, in a ROS 2 parameter YAML (``--params-file``, ``config/euroc.yaml``), in
the code and in every message. ``resolve`` is the one place where values are checked and turns them into typed
``Settings``; the node declares each as a ROS parameter with a ``ParameterDescriptor`` built from this table;
``docs/node.md``'s table is ``markdown_table()``'s output. Choices of ``backbone`` and ``mode`` are the backbone
registry's and the anchoring modes.
"""

from __future__ import annotations

import dataclasses
import difflib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from vi3_core.anchor.options import MODES, AnchorOptions
from vi3_core.backbones import BACKBONES
from vi3_core.dataset.calib import MAX_TIME_OFFSET_S
from vi3_core.errors import DataError, yaml_problem
from vi3_core.init.options import SCALE_SOLVERS, InitOptions
from vi3_core.online.calibration import CalibrationOptions
from vi3_core.online.options import OnlineOptions
from vi3_core.online.stream import MAX_READOUT_S, StreamOptions
from vi3_ros.clip_buffer import ClipBufferOptions
from vi3_ros.settings import (
    GROUPS,
    FlightOptions,
    FrameOptions,
    InputOptions,
    ModelOptions,
    OutputOptions,
    Settings,
)

NODE_NAME = "vi3_node"


@dataclass(frozen=True)
class Param:
    """name: the ROS parameter's name, also the field of ``group`` (an options dataclass) that it sets; range:
    inclusive (lo, hi) for numbers; choices: allowed strings; none_as: the parameter value that stands for the field's
    None (e.g. ``hop`` 0)."""

    name: str
    group: type
    description: str
    range: tuple[float, float] | None = None
    choices: tuple[str, ...] = ()
    none_as: bool | int | float | str | None = None

    @property
    def default(self) -> bool | int | float | str:
        """The field's default (``none_as`` where it is None): the parameter's default, whose type is its type."""
        value = {f.name: f.default for f in dataclasses.fields(self.group)}[self.name]
        return self.none_as if value is None else value

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
                within = f" in [{self.range[0]}, {self.range[1]}]" if self.range is not None else ""
                raise DataError(f"parameter {self.name}: expected {t.__name__}{within}, got {value!r}") from None
            if self.range is not None and not self.range[0] <= value <= self.range[1]:
                raise DataError(f"parameter {self.name}: {value} is outside [{self.range[0]}, {self.range[1]}]")
        else:
            value = str(value)
            if self.choices and value not in self.choices:
                raise DataError(f"parameter {self.name}: {value!r} is not one of {', '.join(self.choices)}")
        return value

    def field_value(self, value: Any) -> Any:
        """The options field's value for the (checked) parameter value: None where it is ``none_as``."""
        return None if self.none_as is not None and value == self.none_as else value


PARAMS: tuple[Param, ...] = (
    # inputs
    Param("image_topic", InputOptions, "camera images (sensor_msgs/Image, mono8/rgb8/bgr8..., or "
          "sensor_msgs/CompressedImage, JPEG/PNG: see image_transport)"),
    Param("image_transport", InputOptions, "message type on image_topic: raw (sensor_msgs/Image), compressed "
          "(sensor_msgs/CompressedImage), auto (node: the type its publishers have, learnt from the ROS graph; "
          "replay: the recording's)", choices=("auto", "raw", "compressed")),
    Param("imu_topic", InputOptions, "IMU samples (sensor_msgs/Imu)"),
    Param("camera_info_topic", InputOptions, "sensor_msgs/CameraInfo with the intrinsics; empty: use calib_file"),
    Param("calib_file", InputOptions, "EuRoC cam0/sensor.yaml or Kalibr camchain-imucam.yaml: intrinsics, distortion "
          "and T_BC (used for whatever camera_info_topic / tf_static do not provide)"),
    Param("rolling_shutter_readout", StreamOptions, "s from the first row's exposure to the last's of a rolling-"
          "shutter camera (a RealSense's colour stream: about 0.025): each frame is turned back to its stamp's "
          "camera by the gyro before the backbone sees it; 0: a global shutter", range=(0.0, MAX_READOUT_S)),
    Param("gyro_prior", StreamOptions, "hand the backbone each clip's camera rotations from the gyro (from the "
          "third clip on, at the window's gyro bias): the classical backbone's bundle adjustment takes them as a "
          "prior, so that short clips that mostly turn do not trade translation for rotation; false: images alone"),
    Param("use_tf_static", InputOptions, "take the camera pose in the IMU frame from /tf_static (imu_frame -> "
          "camera_frame) instead of calib_file"),
    # frames
    Param("clip_frame", FrameOptions, "frame of ~/poses and ~/points: the clip's first camera (OpenCV optical axes)"),
    Param("camera_frame", FrameOptions, "optical frame of the camera (~/depth headers, TF child lookups)"),
    Param("imu_frame", FrameOptions, "IMU (body) frame, parent of camera_frame in /tf_static"),
    Param("publish_tf", FrameOptions, "publish camera_frame -> clip_frame (the clip frame seen from the clip's last "
          "camera) so that the outputs hang off the live TF tree"),
    # online state across clips and the odom trajectory (vi3_core.online)
    Param("online", StreamOptions, "carry the metric state (gravity, gyro bias, velocity) across clips as priors of "
          "each clip's initialisation, and chain the clips into one odom trajectory; false: every clip on its own "
          "(paper)"),
    Param("odom_frame", FrameOptions, "frame of ~/odom and ~/path: continuous, gravity-aligned, z up (REP-105)"),
    Param("base_frame", FrameOptions, "child frame of ~/odom and of the odom TF: the IMU (body) frame"),
    Param("publish_odom_tf", FrameOptions, "publish odom_frame -> base_frame on /tf at each clip's last frame (online "
          "only)"),
    Param("outputs_in_odom", FrameOptions, "express ~/poses and ~/points in odom_frame instead of clip_frame (online "
          "only; a clip that is not chained keeps clip_frame)"),
    Param("imu_odom_rate", OutputOptions, "Hz; ~/odom/imu: the last chained state propagated with every IMU sample, "
          "published at most this often (every sample at the IMU's rate or above); 0: off (online only)",
          range=(0.0, 10000.0)),
    Param("imu_odom_max_sigma", OutputOptions, "m; ~/odom/imu stops, until the next chained clip, once its horizontal "
          "position 1-sigma since the last chained frame exceeds this (a dead-reckoned pose a flight stack should not "
          "use); 0: no limit", range=(0.0, 1000000.0)),
    Param("path_max_poses", OutputOptions, "~/path keeps at most this many latest poses", range=(1, 1_000_000)),
    # odometry for a flight controller (vi3_ros.flight_odom)
    Param("px4_odom", FlightOptions, "publish px4_msgs/VehicleOdometry on px4_odom_topic for PX4's EKF2 (external "
          "vision over uXRCE-DDS: local FRD frame, FRD body, variances, reset_counter, quality; online only; the node "
          "needs px4_msgs)"),
    Param("px4_odom_topic", FlightOptions, "topic of the PX4 odometry (the uXRCE-DDS agent's input topic, under its "
          "namespace if it has one)"),
    Param("mavros_odom", FlightOptions, "publish nav_msgs/Odometry for MAVROS's odometry plugin on mavros_odom_topic "
          "(odom_frame -> vehicle_frame, FLU), which sends it to PX4 or ArduPilot as MAVLink ODOMETRY (online only)"),
    Param("mavros_odom_topic", FlightOptions, "topic of the MAVROS odometry (the odometry plugin's input)"),
    Param("flight_odom_source", FlightOptions, "what feeds px4_odom and mavros_odom: imu (~/odom/imu's states, up to "
          "imu_odom_rate, variances growing with the time since the last chained clip, stopping with it at "
          "imu_odom_max_sigma) or clip (~/odom's, one per chained clip, seconds late with a slow backbone)",
          choices=("imu", "clip")),
    Param("frd_axes", FlightOptions, "the vehicle's forward, right and down axes as signed axes of base_frame (the "
          "IMU body), comma-separated: +x,-y,-z for an FLU IMU, +z,+y,-x for EuRoC's (x up, z forward)"),
    Param("vehicle_frame", FlightOptions, "child frame of the MAVROS odometry: the vehicle's FLU body frame "
          "(MAVROS's base_link_frame_id); its origin is the IMU's"),
    Param("online_window", OnlineOptions, "s; clips starting within this of the newest are fitted "
            "jointly (gravity and biases shared, velocities tied through the IMU, one scale per clip); older ones are "
            "marginalised into a prior", range=(0.5, 60.0)),
    Param("online_max_clips", OnlineOptions, "at most this many clips in the window", range=(2, 100)),
    Param("online_max_bridge", OnlineOptions, "s; the longest gap between clips the IMU bridges "
            "(clips a busy worker dropped); longer, or IMU missing: the window restarts", range=(0.1, 3600.0)),
    Param("online_max_bridge_sigma", OnlineOptions, "m; a clip placed through a bridge whose "
            "position 1-sigma exceeds this starts a new odom segment", range=(0.001, 1000.0)),
    Param("odom_max_scale_sigma", OnlineOptions, "a clip the claim gate refuses goes into ~/odom all the same at the "
          "window's scale where that settled within this relative 1-sigma (counted in ~/odom's covariance; its scale, "
          "depth and points are still not published); at or below max_scale_sigma: claimed clips only",
          range=(0.0, 10.0)),
    Param("online_consistency_p", OnlineOptions, "a clip whose residual in the window (chi-square), or whose own "
          "scale against the window's, has a tail probability below this is inconsistent (rejected)",
          range=(1e-12, 0.5)),
    Param("online_max_rejects", OnlineOptions, "inconsistent clips in a row that restart the "
            "window", range=(1, 1000)),
    Param("online_bg_window", OnlineOptions, "s; the gyro-bias prior is the median of the clips' "
            "own estimates over this long", range=(0.1, 3600.0)),
    Param("shared_frames", OnlineOptions, "each clip starts with the last this many frames of the clip before it that "
          "joined the window, and the two clips' predictions of them (depth, and displacement with 2 or more) link "
          "their scales; they count in clip_length (hop 0 then starts a clip every (clip_length - shared_frames) * "
          "stride frames); 0: no links", range=(0, 63)),
    Param("shared_max_gap", OnlineOptions, "s; the shared frames replace the first frames of a clip that does not "
          "start with them (clips a busy worker dropped) when they end at most this long before it, linking it across "
          "the drop; 0: never (the classical backbone cannot register views seconds apart)", range=(0.0, 60.0)),
    Param("link_sigma_floor", OnlineOptions, "relative 1-sigma added to every scale link for what the spread of its "
          "depth blocks cannot show", range=(0.0, 1.0)),
    # self-calibration of the rig (vi3_core.online.calibration)
    Param("self_calibration", CalibrationOptions, "estimate the camera mount's rotation and the camera-IMU time offset "
          "from the backbone's rotations against the gyro, over the flight; each replaces the configured one once "
          "its sigma passes its limit (false: the calibration as configured)"),
    Param("calib_max_rotation_sigma", CalibrationOptions, "deg; the estimated mount rotation replaces the configured "
          "one once its largest 1-sigma is below this and it differs from the configuration significantly (99 %)",
          range=(0.001, 10.0)),
    Param("calib_max_offset_sigma", CalibrationOptions, "s; the estimated time offset replaces the configured one "
          "once its 1-sigma is below this and it differs from the configuration significantly (99 %)",
          range=(1e-5, 0.1)),
    Param("calib_prior_rotation", CalibrationOptions, "deg; how far the configured mount rotation may be off",
          range=(0.01, 90.0)),
    Param("calib_prior_offset", CalibrationOptions, "s; how far the configured time offset may be off",
          range=(1e-4, 0.5)),
    Param("calib_rotation_walk", CalibrationOptions, "deg/sqrt(s); how fast the mount's rotation may change in flight "
          "(a random walk between clips)", range=(1e-6, 10.0)),
    Param("calib_offset_walk", CalibrationOptions, "s/sqrt(s); how fast the time offset may change in flight",
          range=(1e-8, 0.1)),
    Param("calib_tolerance_rotation", CalibrationOptions, "deg; /diagnostics warns when the estimate is sure the "
          "configured mount is off by more than this", range=(0.0, 90.0)),
    Param("calib_tolerance_offset", CalibrationOptions, "s; /diagnostics warns when the estimate is sure the "
          "configured time offset is off by more than this", range=(0.0, 1.0)),
    # clip buffer
    Param("clip_length", ClipBufferOptions, "frames per clip (n)", range=(2, 64)),
    Param("stride", ClipBufferOptions, "use every stride-th input frame", range=(1, 100)),
    Param("hop", ClipBufferOptions, "input frames between clip starts; 0: clip_length * stride "
            "(non-overlapping)", range=(0, 10000), none_as=0),
    Param("max_frame_gap", ClipBufferOptions, "s; a larger gap between consecutive frames restarts the clip (a "
          "smaller one is bridged: a lost frame a clip needs is replaced by the next); 0: automatic ((stride + 1.5) x "
          "the median recent frame interval: up to stride frames lost in a row are bridged)", range=(0.0, 60.0)),
    Param("time_offset", ClipBufferOptions, "s; camera-IMU time offset, t_imu = t_cam + "
            "time_offset (Kalibr timeshift_cam_imu)", range=(-MAX_TIME_OFFSET_S, MAX_TIME_OFFSET_S)),
    Param("imu_buffer", ClipBufferOptions, "IMU samples kept (bounded buffer)",
            range=(16, 1_000_000)),
    Param("imu_timeout", ClipBufferOptions, "s of camera time a complete clip waits for IMU while no IMU sample "
          "arrives before it is dropped (imu_stalled); an IMU that arrives late but keeps arriving is waited for (up "
          "to max_pending clips)", range=(0.001, 60.0)),
    Param("imu_history", ClipBufferOptions, "s of IMU before the clip kept for the long-window gravity "
            "seed; 0: none", range=(0.0, 60.0)),
    Param("max_pending", ClipBufferOptions, "complete clips waiting for IMU before the oldest is "
            "dropped", range=(1, 1000)),
    # model and anchoring
    Param("backbone", ModelOptions, "3D foundation model", choices=tuple(BACKBONES)),
    Param("device", ModelOptions, "torch device of the backbone (cpu, cuda, cuda:1...)"),
    Param("checkpoint", ModelOptions, "local checkpoint path or Hugging Face id; empty: the backbone's default"),
    Param("threads", ModelOptions, "torch intra-op threads and OpenCV threads of the process (backbone forward, "
          "cond/ttr steps, the classical backbone's tracking) and the classical backbone's plane-sweep threads, set "
          "once at start; 0: min(2, CPUs this process may use)",
          range=(0, 1024)),
    Param("classical_keyframes", ModelOptions, "the classical backbone holds its scale across clips with keyframes "
          "of the clips before (false: each clip's scale is its own; about a sixth less CPU per clip)"),
    Param("mode", StreamOptions, "refinement after the fast init result: init (none), cond (IMU-conditioned), ttr "
          "(test-time refinement)", choices=MODES),
    Param("backbone_delay", ModelOptions, "s added to every clip's processing before the backbone, to emulate a "
          "slower model (testing: what a busy worker drops, how the odometry chains across the gaps)",
          range=(0.0, 3600.0)),
    Param("ttr_steps", AnchorOptions, "TTR optimisation steps", range=(1, 100000)),
    Param("scale_solver", InitOptions, "eiv: backbone positions regressed on the IMU with an error "
            "model, a scale sigma per clip; tls / ols: the paper's Eq. S (no error model; independent clips only)",
            choices=SCALE_SOLVERS),
    Param("max_scale_sigma", InitOptions, "a scale whose relative 1-sigma exceeds this is "
            "not claimed (unobservable)", range=(0.001, 10.0)),
    Param("max_rotation_error", InitOptions, "deg; a clip whose backbone relative rotations "
            "disagree with the bias-corrected gyro by more is a backbone failure (rejected)", range=(0.01, 180.0)),
    Param("accel_noise_density", InitOptions, "m/s^2/sqrt(Hz); accelerometer noise of the "
            "error model (EuRoC's datasheet x 10)", range=(0.0, 10.0)),
    Param("gyro_noise_density", InitOptions, "rad/s/sqrt(Hz); gyro noise of the error model "
            "(EuRoC's datasheet x 5)", range=(0.0, 10.0)),
    Param("gyro_scale_error", InitOptions, "relative error of the integrated rotation in the "
            "error model", range=(0.0, 1.0)),
    Param("accel_bias_sigma", InitOptions, "m/s^2; prior 1-sigma of the accelerometer bias",
            range=(1e-6, 10.0)),
    Param("accel_bias_walk", InitOptions, "m/s^2/sqrt(s); accelerometer bias random walk",
            range=(0.0, 10.0)),
    Param("gyro_bias_walk", InitOptions, "rad/s/sqrt(s); gyro bias random walk",
            range=(0.0, 10.0)),
    Param("accel_matrix", InitOptions, "accelerometer calibration: 9 numbers row-major, specific force = A x "
            "reading (vi3 reference --accel-intrinsics); empty: none"),
    Param("time_offset_sigma", InitOptions, "s; how far the camera-IMU time offset (time_offset, Kalibr "
          "timeshift_cam_imu) may be off: the error model estimates the rest and widens every scale's sigma by what it "
          "cannot rule out", range=(1e-6, 1.0)),
    Param("visual_drift", InitOptions, "the online window estimates a random walk of the backbone's positions "
          "(errors correlated in time) from its clips' residuals and widens the scales' sigmas by it"),
    Param("noise_levels", InitOptions, "the online window estimates the IMU's and the visual noise's levels from its "
          "clips' residuals and fits the scales by errors in variables"),
    Param("scale_rel_floor", InitOptions, "relative scale error the error model does not see "
            "(added to every sigma)", range=(0.0, 1.0)),
    Param("min_accel_rms", InitOptions, "m/s^2; below it scale is unobservable and the clip is "
            "flagged", range=(0.0, 100.0)),
    Param("max_imu_gap", InitOptions, "s; a larger gap between IMU samples inside a clip rejects "
            "it", range=(0.0, 10.0)),
    # outputs
    Param("depth_frames", OutputOptions, "~/depth for every clip frame (all) or only the last",
          choices=("last", "all")),
    Param("points_frames", OutputOptions, "~/points from every clip frame (all) or only the last",
          choices=("last", "all")),
    Param("points_stride", OutputOptions, "~/points keeps every k-th depth pixel in each direction", range=(1, 64)),
    Param("points_conf_quantile", OutputOptions, "~/points drops pixels whose confidence is below this quantile of the "
          "confidences of the clip's pixels with depth (backbone-independent; 0 keeps all)", range=(0.0, 0.99)),
    Param("points_max_depth", OutputOptions, "m; ~/points drops pixels farther than this", range=(0.1, 1000.0)),
    Param("diagnostics_period", OutputOptions, "s between /diagnostics summaries, which carry the dropped input "
          "messages counted by reason (node: timer; replay: bag time)", range=(0.05, 3600.0)),
)


BY_NAME: dict[str, Param] = {p.name: p for p in PARAMS}
_CLASS_ATTR = {cls: attr for attr, cls in GROUPS.items()}


def unknown_parameter(name: str) -> str:
    """What to say about a parameter name that is not one of ``PARAMS``: the closest known name, if one is close."""
    close = difflib.get_close_matches(name, BY_NAME, n=1)
    return f"unknown parameter {name!r}" + (f" (did you mean {close[0]!r}?)" if close else "")


def resolve(overrides: dict[str, Any] | None = None) -> Settings:
    """Every setting at its default but ``overrides`` (parameter name -> value), each checked
    (``Param.check``); an unknown name, a bad value or a combination an options class refuses is a DataError naming
    the parameter."""
    changes = {}
    for name, value in (overrides or {}).items():
        if name not in BY_NAME:
            raise DataError(f"{unknown_parameter(name)}; known: {', '.join(BY_NAME)}")
        p = BY_NAME[name]
        changes[name] = p.field_value(p.check(value))
    try:
        return Settings().replace(**changes)
    except ValueError as exc:  # an options class's own check across its fields
        raise DataError(f"parameters: {exc}") from None


def parameter_values(settings: Settings) -> dict[str, Any]:
    """Every parameter's value in ``settings`` (as a ROS parameter: ``hop`` 0 where the field is None)."""
    out = {}
    for p in PARAMS:
        value = settings.value(p.name)
        out[p.name] = p.none_as if value is None else value
    return out


def load_yaml(path: str | Path, *, node: str = NODE_NAME) -> dict[str, Any]:
    """The ``ros__parameters`` of ``node`` (or of ``/**``) in a ROS 2 parameter file, as written (names checked;
    ``resolve`` checks the values)."""
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise DataError(f"cannot read parameter file {path}: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        raise DataError(f"parameter file {path}: not valid YAML: {yaml_problem(exc)}") from None
    for key in (node, f"/{node}", "/**"):
        section = (doc or {}).get(key) if isinstance(doc, dict) else None
        if isinstance(section, dict) and isinstance(section.get("ros__parameters"), dict):
            params = section["ros__parameters"]
            unknown = [k for k in params if k not in BY_NAME]
            if unknown:
                raise DataError(f"{path}: {unknown_parameter(unknown[0])}")
            return dict(params)
    raise DataError(f"{path}: no '{node}: ros__parameters:' (or '/**') section")


def parse_assignment(text: str) -> tuple[str, str]:
    """``"NAME=VALUE"`` (from the command line) -> (name, value text); ``resolve`` checks and converts the value."""
    name, sep, value = text.partition("=")
    if not sep:
        raise DataError(f"--param {text!r}: expected NAME=VALUE with NAME one of {', '.join(BY_NAME)}")
    if name not in BY_NAME:
        raise DataError(f"--param {text!r}: {unknown_parameter(name)}; known: {', '.join(BY_NAME)}")
    return name, value


def settings_from_cli(params_file: str | None, assignments: list[str], named: dict[str, Any] | None = None) -> Settings:
    """Settings of a ``vi3`` command: defaults < ``--params-file`` < ``--param NAME=VALUE`` < the command's named
    options (``named``: parameter name -> value, None where the option was not given), checked once."""
    overrides = load_yaml(params_file) if params_file else {}
    overrides.update(parse_assignment(a) for a in assignments)
    overrides.update({k: v for k, v in (named or {}).items() if v is not None})
    return resolve(overrides)


def markdown_table() -> str:
    """The parameter table of docs/node.md."""
    rows = ["| name | type | default | range / choices | description |", "|---|---|---|---|---|"]
    for p in PARAMS:
        allowed = " \\| ".join(p.choices) if p.choices else (f"[{p.range[0]}, {p.range[1]}]" if p.range else "")
        default = f'"{p.default}"' if isinstance(p.default, str) else str(p.default).lower() \
            if isinstance(p.default, bool) else str(p.default)
        rows.append(f"| `{p.name}` | {p.type.__name__} | {default} | {allowed} | {p.description} |")
    return "\n".join(rows)


def _check_table() -> None:
    """Every parameter names a field of its group, and no name is in two groups (one name per setting)."""
    for p in PARAMS:
        if p.group not in _CLASS_ATTR or p.name not in {f.name for f in dataclasses.fields(p.group)}:
            raise AssertionError(f"parameter {p.name}: no field of that name in {p.group.__name__}")
    if len(BY_NAME) != len(PARAMS):
        raise AssertionError("a parameter is declared twice")


_check_table()
