"""A Foxglove Studio (1.48) layout for one annotated log: its own topics in our panels.

The panels: the live camera image with our annotations on it, the match image beside it, a
3-D panel (the trajectory, the loop lines, the current loop closure, the current pose, the
`optimize` paths and a ground-truth pose topic, those the log has), and the loop closures'
messages. Lichtblick opens the same layout (it migrates the Image panels as it loads them).

The 3-D panel follows the frame the markers are drawn in: the first frame_id of the run's
odometry (`map` when it has none), read from its first message only.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ..annotations.reader import read_run_metadata
from ..annotations.records import LOOP_CLOSURE, OUR_TOPIC_PREFIX, RunMetadata
from ..errors import SourceError
from ..sinks.atomic import atomic_output
from ..sinks.visualization import (
    ANNOTATIONS_TOPIC,
    CURRENT_POSE_TOPIC,
    DEFAULT_FRAME_ID,
    LOOP_LINES_TOPIC,
    MARKERS_TOPIC,
    MATCH_ANNOTATIONS_TOPIC,
    MATCH_MARKER_TOPIC,
    match_topic,
)
from ..sources import opened, refuse_stream
from ..sources.base import Source
from ..sources.poses import ODOMETRY, POSE_TYPES, canonical_type, default_pose_topic, frame_id_of
from .base import ODOMETRY_PATH_TOPIC, OPTIMIZED_PATH_TOPIC

QUERY_PANEL, MATCH_PANEL = "ImageViewPanel!query", "ImageViewPanel!match"
SCENE_PANEL, LOOPS_PANEL = "3D!loops", "RawMessages!loop"
# The 3-D panel's settings of each topic drawn, in drawing order; a ground-truth topic (not
# ours) takes GROUND_TRUTH. Colours no other drawing has: the paths are told apart by them.
SHOWN = {"visible": True}
TOPIC_SETTINGS: dict[str, dict[str, Any]] = {
    MARKERS_TOPIC: SHOWN,
    MATCH_MARKER_TOPIC: SHOWN,
    LOOP_LINES_TOPIC: SHOWN,
    ODOMETRY_PATH_TOPIC: {
        **SHOWN, "type": "line", "lineWidth": 0.4, "gradient": ["#ffb000", "#ffb000"],
    },
    OPTIMIZED_PATH_TOPIC: {
        **SHOWN, "type": "line", "lineWidth": 0.2, "gradient": ["#ff00ff", "#ff00ff"],
    },
    CURRENT_POSE_TOPIC: {
        **SHOWN, "type": "arrow", "arrowScale": [2.0, 0.5, 0.5], "color": "#8000ff",
    },
}  # fmt: skip
GROUND_TRUTH = {**SHOWN, "type": "arrow", "arrowScale": [1.5, 0.3, 0.3], "color": "#00e0ff"}
# The pose types the 3-D panel draws (not nav_msgs/Odometry): a ground-truth topic's.
DRAWN_POSE_TYPES = tuple(kind for kind in POSE_TYPES if kind != ODOMETRY)
GRID = {
    "visible": True, "frameLocked": True, "label": "Grid", "instanceId": "grid",
    "layerId": "foxglove.Grid", "size": 100, "divisions": 20, "lineWidth": 1,
    "color": "#248eff", "position": [0, 0, 0], "rotation": [0, 0, 0], "order": 1,
}  # fmt: skip
# Seen from above, the samples' 20 m drive in view.
CAMERA_STATE = {
    "perspective": False, "distance": 28, "phi": 0, "thetaOffset": 0, "targetOffset": [0, 12, 0],
}  # fmt: skip


def layout_of(log: str | Path) -> dict[str, Any]:
    """The layout of an annotated MCAP (module docstring). Raises SourceError when the file
    is missing, unreadable or not annotated by doseqslam-logs."""
    path = Path(log)
    refuse_stream(path)
    if not path.is_file():
        raise SourceError(f"{path}: no such file")
    metadata = read_run_metadata(path)
    if metadata is None:
        raise SourceError(f"{path}: not annotated by doseqslam-logs (no 'doseqslam' record)")
    with opened(path) as source:
        types = {c.topic: canonical_type(c.message_type) for c in source.channels()}
        pose_topic = metadata.odometry_topic or default_pose_topic(source)
        frame = _first_frame_id(source, pose_topic) if pose_topic in types else ""
    return _layout(metadata, types, pose_topic or "", frame or DEFAULT_FRAME_ID)


def write_layout(log: str | Path, output: str | Path) -> dict[str, Any]:
    """Writes `layout_of(log)` to `output` as JSON, atomically; returns the layout."""
    layout = layout_of(log)
    with atomic_output(output) as stream:
        stream.write(layout_json(layout).encode())
    return layout


def layout_json(layout: dict[str, Any]) -> str:
    """The layout's text, as docs/foxglove_layout.json holds it."""
    return json.dumps(layout, indent=2) + "\n"


def _first_frame_id(source: Source, topic: str) -> str:
    """The frame_id of the topic's first decodable message ("" when none says one)."""
    for message in source.messages(topic):
        if message.message is not None:
            return frame_id_of(message.message)
    return ""


def _ground_truth_topic(types: dict[str, str], pose_topic: str) -> str | None:
    """The log's first pose topic the 3-D panel draws, other than the odometry and ours."""
    others = (t for t in types if t != pose_topic and not t.startswith(OUR_TOPIC_PREFIX))
    return next((topic for topic in others if types[topic] in DRAWN_POSE_TYPES), None)


def _scene_topics(types: dict[str, str], pose_topic: str) -> dict[str, dict[str, Any]]:
    topics = {topic: dict(s) for topic, s in TOPIC_SETTINGS.items() if topic in types}
    ground_truth = _ground_truth_topic(types, pose_topic)
    if ground_truth is not None:
        topics[ground_truth] = dict(GROUND_TRUTH)
    return topics


def _image_panel(topic: str, annotations: str, types: dict[str, str]) -> dict[str, Any]:
    return {
        "cameraTopic": topic,
        "enabledMarkerTopics": [annotations] if annotations in types else [],
        "synchronize": False,
        "mode": "fit",
    }


def _layout(
    metadata: RunMetadata, types: dict[str, str], pose_topic: str, frame: str
) -> dict[str, Any]:
    camera = metadata.image_topic
    scene = {
        "followTf": frame,
        "scene": {},
        "transforms": {},
        "topics": _scene_topics(types, pose_topic),
        "layers": {"grid": dict(GRID)},
        "cameraState": dict(CAMERA_STATE),
        "publish": {"type": "point"},
    }
    loops = {"topicPath": LOOP_CLOSURE.topic, "diffEnabled": False, "expansion": "all"}
    return {
        "configById": {
            QUERY_PANEL: _image_panel(camera, ANNOTATIONS_TOPIC, types),
            MATCH_PANEL: _image_panel(match_topic(camera), MATCH_ANNOTATIONS_TOPIC, types),
            SCENE_PANEL: scene,
            LOOPS_PANEL: loops,
        },
        "globalVariables": {},
        "userNodes": {},
        "playbackConfig": {"speed": 1},
        "layout": {
            "direction": "column",
            "first": _split("row", QUERY_PANEL, MATCH_PANEL, 50),
            "second": _split("row", SCENE_PANEL, LOOPS_PANEL, 65),
            "splitPercentage": 50,
        },
    }


def _split(direction: str, first: str, second: str, percent: int) -> dict[str, Any]:
    return {"direction": direction, "first": first, "second": second, "splitPercentage": percent}
