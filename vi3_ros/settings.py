"""The node's settings, typed: one options dataclass per concern, each field named as its ROS parameter
(``vi3_ros.params`` declares them), and ``Settings``, the groups together, which the node, replay and the CLI hand to
the ``Pipeline``. The core's options (``StreamOptions``, ``OnlineOptions``, ``InitOptions``, ``AnchorOptions``) and the
clip buffer's are groups too; the ones here are the ROS shell's own."""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from typing import Any

from vi3_core.anchor.options import AnchorOptions
from vi3_core.init.options import InitOptions
from vi3_core.online.calibration import CalibrationOptions
from vi3_core.online.options import OnlineOptions
from vi3_core.online.stream import StreamOptions
from vi3_ros.clip_buffer import ClipBufferOptions
from vi3_ros.flight_frames import FLU_AXES, frd_rotation


@dataclass(frozen=True)
class InputOptions:
    """Where the stream comes from: topics, image transport, and the calibration's sources."""

    image_topic: str = "/cam0/image_raw"
    image_transport: str = "auto"
    imu_topic: str = "/imu0"
    camera_info_topic: str = ""
    calib_file: str = ""
    use_tf_static: bool = False


@dataclass(frozen=True)
class FrameOptions:
    """The frame ids of the outputs and of the TF lookups, and which transforms are published."""

    clip_frame: str = "vi3_clip"
    camera_frame: str = "cam0"
    imu_frame: str = "imu0"
    publish_tf: bool = False
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    publish_odom_tf: bool = False
    outputs_in_odom: bool = False


@dataclass(frozen=True)
class OutputOptions:
    """What is published beyond each clip's poses: ``~/odom/imu`` (Hz, m), ``~/path``, depth and point clouds, and the
    period (s) of the ``/diagnostics`` summary."""

    imu_odom_rate: float = 200.0
    imu_odom_max_sigma: float = 1.0
    path_max_poses: int = 5000
    depth_frames: str = "last"
    points_frames: str = "last"
    points_stride: int = 2
    points_conf_quantile: float = 0.3
    points_max_depth: float = 20.0
    diagnostics_period: float = 1.0

    @property
    def all_depth(self) -> bool:
        """Whether every frame's depth is published (``depth_frames`` or ``points_frames`` all)."""
        return self.depth_frames == "all" or self.points_frames == "all"


#: A ROS 2 topic name: absolute or relative tokens of letters, digits and underscores, not starting with a digit.
_TOPIC = re.compile(r"/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*")


@dataclass(frozen=True)
class FlightOptions:
    """Odometry for a flight controller (``vi3_ros.flight_odom``): PX4 over uXRCE-DDS (``px4_msgs/VehicleOdometry``
    on ``px4_odom_topic``), MAVROS's odometry plugin (``nav_msgs/Odometry`` on ``mavros_odom_topic``, for PX4 or
    ArduPilot over MAVLink), which odometry feeds them (``imu``: ``~/odom/imu``'s states; ``clip``: ``~/odom``'s), the
    vehicle's forward-right-down axes as signed axes of ``base_frame`` (``vi3_ros.flight_frames.frd_rotation``) and
    the child frame of the MAVROS odometry (the vehicle's FLU body frame, MAVROS's ``base_link``)."""

    px4_odom: bool = False
    px4_odom_topic: str = "/fmu/in/vehicle_visual_odometry"
    mavros_odom: bool = False
    mavros_odom_topic: str = "/mavros/odometry/out"
    flight_odom_source: str = "imu"
    frd_axes: str = FLU_AXES
    vehicle_frame: str = "base_link"

    def __post_init__(self) -> None:
        frd_rotation(self.frd_axes)
        for name in ("px4_odom_topic", "mavros_odom_topic"):
            if not _TOPIC.fullmatch(getattr(self, name)):
                raise ValueError(f"{name} {getattr(self, name)!r} is not a ROS topic name (e.g. /fmu/in/"
                                 "vehicle_visual_odometry: letters, digits and _ between slashes)")
        if not self.vehicle_frame.strip("/"):
            raise ValueError("vehicle_frame is empty: name the vehicle's FLU body frame (MAVROS's base_link)")

    @property
    def outputs_on(self) -> dict[str, str]:
        """The flight controllers' outputs that are on (``px4_odom``, ``mavros_odom``, in that order) -> topic."""
        return {key: getattr(self, f"{key}_topic") for key in ("px4_odom", "mavros_odom") if getattr(self, key)}


@dataclass(frozen=True)
class ModelOptions:
    """The backbone: its name, torch device and checkpoint, the process's torch threads (0: automatic), a delay (s)
    added before it on every clip (testing a slower model), and whether the ``classical`` backbone holds its scale
    across clips with keyframes (``ClassicalBackbone``'s ``keyframes``)."""

    backbone: str = "classical"
    device: str = "cpu"
    checkpoint: str = ""
    threads: int = 0
    backbone_delay: float = 0.0
    classical_keyframes: bool = True

    def __post_init__(self) -> None:
        self.backbone_options()

    def backbone_options(self, name: str | None = None) -> dict[str, Any]:
        """``make_backbone``'s options for backbone ``name`` (None: this one's): the classical backbone's
        ``keyframes``; ValueError where an option is set that the backbone does not take."""
        name = name or self.backbone
        if name == "classical":
            return {"keyframes": self.classical_keyframes}
        if not self.classical_keyframes:
            raise ValueError(f"classical_keyframes is false, but the backbone is {name}: it applies to the classical "
                             "backbone only")
        return {}


@dataclass(frozen=True)
class Settings:
    """Every setting of a stream, by group; ``value(name)`` / ``replace(name=value)`` address one by its parameter
    name (``group_attr`` knows its group)."""

    inputs: InputOptions = field(default_factory=InputOptions)
    frames: FrameOptions = field(default_factory=FrameOptions)
    outputs: OutputOptions = field(default_factory=OutputOptions)
    flight: FlightOptions = field(default_factory=FlightOptions)
    model: ModelOptions = field(default_factory=ModelOptions)
    buffer: ClipBufferOptions = field(default_factory=ClipBufferOptions)
    stream: StreamOptions = field(default_factory=StreamOptions)
    online: OnlineOptions = field(default_factory=OnlineOptions)
    init: InitOptions = field(default_factory=InitOptions)
    anchor: AnchorOptions = field(default_factory=AnchorOptions)
    calibration: CalibrationOptions = field(default_factory=CalibrationOptions)

    def value(self, name: str) -> Any:
        """The value of parameter ``name`` (as the options field holds it: ``hop`` None where the parameter says 0)."""
        return getattr(getattr(self, group_attr(name)), name)

    def replace(self, **changes: Any) -> Settings:
        """These settings with the parameters in ``changes`` set (values as the options fields take them)."""
        groups: dict[str, dict[str, Any]] = {}
        for name, value in changes.items():
            groups.setdefault(group_attr(name), {})[name] = value
        return dataclasses.replace(self, **{g: dataclasses.replace(getattr(self, g), **v) for g, v in groups.items()})


GROUPS: dict[str, type] = {f.name: f.default_factory for f in dataclasses.fields(Settings)}  # attribute -> class
_ATTR = {name: attr for attr, cls in GROUPS.items() for name in (f.name for f in dataclasses.fields(cls))}


def group_attr(name: str) -> str:
    """The ``Settings`` attribute of the group that holds the option ``name`` (KeyError when none does)."""
    return _ATTR[name]


__all__ = ["GROUPS", "FlightOptions", "FrameOptions", "InputOptions", "ModelOptions", "OutputOptions", "Settings",
           "group_attr"]
