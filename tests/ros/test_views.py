"""The views in config/ (RViz2's ``vi3.rviz``, Foxglove's ``vi3_foxglove.json``) against what ``make demo``
writes: every topic a panel names is in the demo's MCAP with a type that panel shows, every field a plot reads exists,
and the 3D views' frame holds the scene; colcon installs both files."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import pytest
import yaml
from rosbags.highlevel import AnyReader

from msg_adapters.poses import tf_message_to_list
from vi3_ros.cli import main as vi3_main
from vi3_ros.commands.demo import BUNDLED, VIEWS, demo_inputs, replay_args

pytestmark = pytest.mark.slow  # the demo's replay

REPO = Path(__file__).resolve().parents[2]
RVIZ, FOXGLOVE = VIEWS
IMAGE = {"sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"}
#: What each RViz2 display class shows.
RVIZ_TYPES = {"rviz_default_plugins/Image": IMAGE,
              "rviz_default_plugins/PointCloud2": {"sensor_msgs/msg/PointCloud2"},
              "rviz_default_plugins/PoseArray": {"geometry_msgs/msg/PoseArray"},
              "rviz_default_plugins/Odometry": {"nav_msgs/msg/Odometry"},
              "rviz_default_plugins/Path": {"nav_msgs/msg/Path"}}
#: What Foxglove's 3D panel draws from a topic.
SCENE_TYPES = {"sensor_msgs/msg/PointCloud2", "geometry_msgs/msg/PoseArray", "nav_msgs/msg/Odometry",
               "nav_msgs/msg/Path"}


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> tuple[dict[str, str], dict[str, object]]:
    """({topic: type}, {topic: its first message}) of the MCAP ``vi3 demo`` writes (its replay of the bundled bag)."""
    bag, _, calib = demo_inputs(BUNDLED)
    out = tmp_path_factory.mktemp("demo") / "vi3_output.mcap"
    assert vi3_main([*replay_args(bag, out, backbone="classical", calib=calib), "--no-progress"]) == 0
    first: dict[str, object] = {}
    with AnyReader([out]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        for c, _, raw in reader.messages():
            first.setdefault(c.topic, reader.deserialize(raw, c.msgtype))
    return types, first


def _frames(first: dict[str, object]) -> set[str]:
    """Frames the demo's /tf connects."""
    return {f for T in tf_message_to_list(first["/tf"]) for f in T[1:3]}


def test_every_rviz_display_has_its_topic_in_the_demo(demo):
    types, first = demo
    config = yaml.safe_load(RVIZ.read_text())["Visualization Manager"]
    fixed = config["Global Options"]["Fixed Frame"]
    assert fixed in _frames(first) and types["/tf"] == "tf2_msgs/msg/TFMessage"
    shown = set()
    for display in config["Displays"]:
        topic = display.get("Topic", {}).get("Value")
        if topic is None:
            assert display["Class"] in ("rviz_default_plugins/Grid", "rviz_default_plugins/TF"), display
            continue
        assert types.get(topic) in RVIZ_TYPES[display["Class"]], (display["Name"], topic, types.get(topic))
        if display["Class"] != "rviz_default_plugins/Image":  # drawn in the fixed frame
            assert first[topic].header.frame_id == fixed, (topic, first[topic].header.frame_id)
        shown.add(types[topic])
    assert shown == set().union(*RVIZ_TYPES.values()) - {"sensor_msgs/msg/CompressedImage"}


def _resolve(msg: object, path: str) -> object:
    for name in path.split("."):
        msg = getattr(msg, name)
    return msg


def test_every_foxglove_panel_has_its_topic_in_the_demo(demo):
    types, first = demo
    layout = json.loads(FOXGLOVE.read_text())
    panels = layout["configById"]
    assert {kind.split("!")[0] for kind in panels} == {"3D", "Image", "Plot", "RawMessages"}
    for key, config in panels.items():
        kind = key.split("!")[0]
        if kind == "3D":
            assert config["followTf"] in _frames(first)
            for topic in config["topics"]:
                assert types.get(topic) in SCENE_TYPES, (topic, types.get(topic))
                assert first[topic].header.frame_id == config["followTf"], topic
        elif kind == "Image":
            assert types.get(config["imageMode"]["imageTopic"]) in IMAGE, config
        elif kind == "Plot":
            for line in config["paths"]:
                topic, _, field = line["value"].partition(".")
                assert isinstance(_resolve(first[topic], field), float), line["value"]
        else:
            assert config["topicPath"] in types
    # the layout places every panel it configures
    placed = json.dumps(layout["layout"])
    assert all(f'"{key}"' in placed for key in panels)


def test_colcon_installs_the_views():
    call = next(n for n in ast.walk(ast.parse((REPO / "setup.py").read_text()))
                if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "setup")
    data_files = next(k.value for k in call.keywords if k.arg == "data_files")
    text = ast.unparse(data_files)
    assert "glob('config/*.rviz')" in text and "glob('config/*.json')" in text
    assert RVIZ.parent == FOXGLOVE.parent == REPO / "config" and RVIZ.suffix == ".rviz" and FOXGLOVE.suffix == ".json"
