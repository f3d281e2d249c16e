"""Lichtblick, the open-source fork of Foxglove Studio: no runnable build of it is on the
package registries (npm's `@lichtblick/suite` holds the extension API's TypeScript sources
only; the app ships as a desktop installer or a container image), so its rules are checked
here, as Lichtblick's own source states them (github.com/lichtblick-suite/lichtblick at
66adecb99), on our layout (docs/foxglove_layout.json) and on what annotate and optimize write:

- Lichtblick migrates the layout as it loads it (services/migrateLayout/migratePanelsState.ts:
  the legacy Image panel "ImageViewPanel" becomes the 3-D-based "Image" panel); after that,
  every panel is one of its panel types (panels/index.ts);
- the migrated Image panels show the same image topic and image annotations;
- every topic a panel names is in the output, with a schema that panel renders (the
  renderables' `schemaNames`: ThreeDeeRender/ros.ts and foxglove.ts datatypes, in every
  spelling addRosDataType and addFoxgloveSchema add), and the 3-D topic settings use only the
  keys of that renderable's settings type (LayerSettingsEntity, LayerSettingsMarker,
  LayerSettingsPose, LayerSettingsPoseArray) with values of their types.

The JSON schemas' rules (parseJsonSchema) are checked in test_viewer_schemas.py.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from doseqslam_logs.cli.main import main

REPO = Path(__file__).resolve().parents[1]
LAYOUT = REPO / "docs" / "foxglove_layout.json"

# panels/index.ts: every panel type Lichtblick builds.
PANEL_TYPES = {
    "3D", "DiagnosticStatusPanel", "DiagnosticSummary", "Image", "Indicator", "Gauge", "Teleop",
    "map", "Parameters", "Plot", "PieChart", "Publish", "CallService", "RawMessages",
    "RawMessagesVirtual", "RosOut", "StateTransitions", "Table", "TopicGraph", "SourceInfo",
    "GlobalVariableSliderPanel", "NodePlayground", "Tab", "PlaybackPerformance",
}  # fmt: skip


def ros_types(*names: str) -> set[str]:
    """ros.ts addRosDataType: the ROS 1 name, its ROS 2 spelling and its protobuf one."""
    out = set()
    for name in names:
        base, leaf = name.split("/", 1)
        out |= {name, f"{base}/msg/{leaf}", "ros." + name.replace("/", ".")}
    return out


def foxglove_types(*names: str) -> set[str]:
    """foxgloveSchemas.ts addFoxgloveSchema: foxglove.X, foxglove_msgs/X, foxglove_msgs/msg/X."""
    out = set()
    for name in names:
        leaf = name.split(".", 1)[1]
        out |= {name, f"foxglove_msgs/{leaf}", f"foxglove_msgs/msg/{leaf}"}
    return out


BASE_SETTINGS = {"visible": bool, "frameLocked": bool}
ENTITY = {"showOutlines": bool, "color": str, "selectedIdVariable": str}
DISPLAY = {"axisScale": float, "arrowScale": list}
# The 3-D panel's renderables: the schemas each takes, and its topic settings' keys and types.
RENDERABLES: dict[str, tuple[set[str], dict[str, Any]]] = {
    "SceneEntities": (foxglove_types("foxglove.SceneUpdate"), ENTITY),
    "Markers": (
        ros_types("visualization_msgs/MarkerArray", "visualization_msgs/Marker"),
        {**ENTITY, "namespaces": dict},
    ),
    "Poses": (
        ros_types("geometry_msgs/PoseStamped", "geometry_msgs/PoseWithCovarianceStamped")
        | foxglove_types("foxglove.PoseInFrame"),
        {
            **DISPLAY,
            "type": ("axis", "arrow"),
            "color": str,
            "showCovariance": bool,
            "covarianceColor": str,
        },
    ),
    "PoseArrays": (
        ros_types("geometry_msgs/PoseArray", "nav_msgs/Path")
        | foxglove_types("foxglove.PosesInFrame"),
        {**DISPLAY, "type": ("axis", "arrow", "line"), "lineWidth": float, "gradient": list},
    ),
}
IMAGES = ros_types("sensor_msgs/Image", "sensor_msgs/CompressedImage") | foxglove_types(
    "foxglove.RawImage", "foxglove.CompressedImage"
)
IMAGE_ANNOTATIONS = foxglove_types("foxglove.ImageAnnotations") | ros_types(
    "visualization_msgs/ImageMarker", "visualization_msgs/ImageMarkerArray"
)
COLOR = re.compile(r"#[0-9a-fA-F]{6}([0-9a-fA-F]{2})?")


def leaves(node: Any) -> list[str]:
    """The panel ids of a react-mosaic layout tree (util/layout.ts getLeaves)."""
    if isinstance(node, str):
        return [node]
    assert set(node) <= {"direction", "first", "second", "splitPercentage"}, node
    assert node["direction"] in ("row", "column"), node
    return leaves(node["first"]) + leaves(node["second"])


def panel_type(panel_id: str) -> str:
    return panel_id.split("!")[0]  # util/layout.ts getPanelTypeFromId


def migrated(layout: dict[str, Any]) -> dict[str, Any]:
    """migrateLegacyToNewImagePanels: each ImageViewPanel replaced by an Image panel whose
    imageMode shows its cameraTopic and its enabledMarkerTopics as visible annotations."""
    configs, tree = dict(layout["configById"]), json.dumps(layout["layout"])
    for panel_id in [p for p in leaves(layout["layout"]) if panel_type(p) == "ImageViewPanel"]:
        legacy = configs.pop(panel_id)
        markers = legacy.get("enabledMarkerTopics", [])
        new_id = "Image!" + panel_id.split("!", 1)[1]
        configs[new_id] = {
            "imageMode": {
                "imageTopic": legacy.get("cameraTopic"),
                "synchronize": legacy.get("synchronize"),
                "annotations": {topic: {"visible": True} for topic in markers},
            }
        }
        tree = tree.replace(json.dumps(panel_id), json.dumps(new_id))
    return {**layout, "configById": configs, "layout": json.loads(tree)}


def topics_of(*logs: Path) -> dict[str, str]:
    """topic -> schema name of every channel of the logs."""
    found: dict[str, str] = {}
    for log in logs:
        with log.open("rb") as stream:
            summary = make_reader(stream).get_summary()
        assert summary is not None
        for channel in summary.channels.values():
            found[channel.topic] = summary.schemas[channel.schema_id].name
    return found


def check_setting(name: str, value: Any, kind: Any) -> None:
    if isinstance(kind, tuple):
        assert value in kind, (name, value)
    elif kind is float:
        assert isinstance(value, (int, float)) and not isinstance(value, bool), (name, value)
    else:
        assert isinstance(value, kind), (name, value)
    if name.lower().endswith("color"):
        assert COLOR.fullmatch(value), (name, value)
    if name == "gradient":
        assert len(value) == 2 and all(COLOR.fullmatch(c) for c in value), value


@pytest.fixture(scope="module")
def layout() -> dict[str, Any]:
    data: dict[str, Any] = json.loads(LAYOUT.read_text())
    return data


@pytest.fixture(scope="module")
def output_topics(
    annotated_sample: Callable[..., Path], tmp_path_factory: pytest.TempPathFactory
) -> dict[str, str]:
    """The topics of the ROS 2 sample's output and of its optimized copy (the paths)."""
    pytest.importorskip("gtsam")
    annotated = annotated_sample("drive_loops.ros2.mcap")
    optimized = tmp_path_factory.mktemp("lichtblick") / "optimized.mcap"
    assert main(["optimize", str(annotated), "-o", str(optimized)]) == 0
    return topics_of(annotated, optimized)


def test_every_panel_of_the_migrated_layout_is_a_lichtblick_panel(layout: dict[str, Any]) -> None:
    before = leaves(layout["layout"])
    assert {panel_type(p) for p in before} - PANEL_TYPES == {"ImageViewPanel"}  # it migrates
    after = migrated(layout)
    assert {panel_type(p) for p in leaves(after["layout"])} <= PANEL_TYPES
    assert all(p in after["configById"] for p in leaves(after["layout"]))
    assert len(leaves(after["layout"])) == len(before)


def test_the_migrated_image_panels_show_the_same_topics(layout: dict[str, Any]) -> None:
    legacy = {
        config["cameraTopic"]: set(config.get("enabledMarkerTopics", []))
        for panel_id, config in layout["configById"].items()
        if panel_type(panel_id) == "ImageViewPanel"
    }
    configs = migrated(layout)["configById"].items()
    shown = {
        c["imageMode"]["imageTopic"]: set(c["imageMode"]["annotations"])
        for panel_id, c in configs
        if panel_type(panel_id) == "Image"
    }
    assert shown == legacy and len(shown) == 2  # the live frame and the match


@pytest.mark.slow
def test_every_topic_of_the_layout_is_in_the_output_with_a_schema_lichtblick_renders(
    layout: dict[str, Any], output_topics: dict[str, str]
) -> None:
    check_topics_render(layout, output_topics)


def check_topics_render(layout: dict[str, Any], output_topics: dict[str, str]) -> None:
    """Every topic the migrated layout names is in `output_topics` with a schema its panel
    renders, and the 3-D settings are those of that renderable."""
    for panel_id, config in migrated(layout)["configById"].items():
        kind = panel_type(panel_id)
        if kind == "Image":
            image = config["imageMode"]
            assert output_topics[image["imageTopic"]] in IMAGES, image
            for topic in image["annotations"]:
                assert output_topics[topic] in IMAGE_ANNOTATIONS, topic
        elif kind == "3D":
            for topic, settings in config["topics"].items():
                schema = output_topics[topic]
                found = [keys for names, keys in RENDERABLES.values() if schema in names]
                assert len(found) == 1, (topic, schema)
                allowed = {**BASE_SETTINGS, **found[0]}
                for name, value in settings.items():
                    assert name in allowed, (topic, name)
                    check_setting(name, value, allowed[name])
        elif kind == "RawMessages":
            assert config["topicPath"].split(".")[0] in output_topics, config


def test_the_checks_refuse_what_lichtblick_would_not_draw() -> None:
    # A setting of another renderable (a Pose's colour on a Path), a colour that is not hex,
    # a display type the renderable lacks: each is refused.
    path_keys = {**BASE_SETTINGS, **RENDERABLES["PoseArrays"][1]}
    assert "color" not in path_keys
    with pytest.raises(AssertionError):
        check_setting("gradient", ["magenta", "#ff00ff"], path_keys["gradient"])
    with pytest.raises(AssertionError):
        check_setting("type", "line", RENDERABLES["Poses"][1]["type"])
    unknown = {"layout": "Plot3D!a", "configById": {"Plot3D!a": {}}}
    assert panel_type(leaves(migrated(unknown)["layout"])[0]) not in PANEL_TYPES
