"""The visualization channels' messages in each output profile, as the viewers expect them.

Foxglove and Lichtblick draw a message with no custom panel when its schema is one they know:
`visualization_msgs/MarkerArray` and `foxglove_msgs/ImageAnnotations` in the ROS profiles,
`foxglove.SceneUpdate` and `foxglove.ImageAnnotations` (JSON) in every other profile; a pose
is `geometry_msgs/PoseStamped` in the ROS profiles, `foxglove.PoseInFrame` (JSON) otherwise. The
builders here take the same plain description (lines in a frame, texts on an image) and give
each profile's schema and bytes. Definitions come from rosbags' type stores
(visualization_msgs) and from `schemas/` (foxglove_msgs, the JSON schemas).
"""

from __future__ import annotations

import json
from abc import ABC, abstractmethod
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from ..annotations.records import time_dict
from ..annotations.schema_files import read_schema
from .encoders import RosBuilder

Point3 = tuple[float, float, float]
Quaternion = tuple[float, float, float, float]  # x, y, z, w
Rgba = tuple[float, float, float, float]
FOXGLOVE_MSGS = ("Color", "Point2", "CircleAnnotation", "PointsAnnotation", "TextAnnotation")
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TIME = "builtin_interfaces/msg/Time"
IMAGE_ANNOTATIONS = "foxglove_msgs/msg/ImageAnnotations"
LINE_STRIP, LINE_LIST = "strip", "list"
_ROS_MARKER_TYPES = {LINE_STRIP: 4, LINE_LIST: 5}  # visualization_msgs/Marker
_SCENE_LINE_TYPES = {LINE_STRIP: 0, LINE_LIST: 2}  # foxglove.LinePrimitive
_ROS_MARKER_DELETE = 2  # visualization_msgs/Marker action
_SCENE_MATCHING_ID = 0  # foxglove.SceneEntityDeletion type
POINTS, LINE_LOOP_POINTS = 1, 2  # foxglove PointsAnnotation types


@dataclass(frozen=True)
class Lines:
    """One drawing of lines in the 3-D scene: a trajectory or one loop closure."""

    namespace: str  # with `number`, what names it (a later drawing of the same name replaces it)
    number: int
    kind: str  # LINE_STRIP or LINE_LIST
    points: Sequence[Point3]
    color: Rgba
    thickness_m: float


@dataclass(frozen=True)
class Text:
    """A text on an image, at pixel (x, y) from its top left corner."""

    x: float
    y: float
    text: str
    font_size: float
    color: Rgba
    background: Rgba


@dataclass(frozen=True)
class Badge:
    """A filled square on an image, its top left corner at pixel (x, y)."""

    x: float
    y: float
    size: float
    color: Rgba


@dataclass(frozen=True)
class Dots:
    """Points on an image, each a filled dot of radius `size` pixels; (x, y) from the image's
    top left corner (the top left pixel's centre is (0.5, 0.5))."""

    points: Sequence[tuple[float, float]]
    color: Rgba
    size: float


@dataclass(frozen=True)
class SchemaInfo:
    name: str
    encoding: str
    data: bytes
    channel_metadata: dict[str, str]


class VisualEncoder(ABC):
    """Schemas and bytes of the 3-D lines and image texts in one profile."""

    message_encoding: ClassVar[str]

    @abstractmethod
    def scene_schema(self) -> SchemaInfo: ...

    @abstractmethod
    def annotations_schema(self) -> SchemaInfo: ...

    @abstractmethod
    def pose_schema(self) -> SchemaInfo: ...

    @abstractmethod
    def scene(self, frame_id: str, time_ns: int, lines: Sequence[Lines]) -> bytes: ...

    @abstractmethod
    def pose(self, frame_id: str, time_ns: int, position: Point3, orientation: Quaternion) -> bytes:
        """One pose in a frame, stamped at `time_ns`."""

    @abstractmethod
    def deletion(self, frame_id: str, time_ns: int, namespace: str, number: int) -> bytes:
        """A scene message that removes the drawing named (namespace, number) of its topic."""

    @abstractmethod
    def annotations(
        self,
        time_ns: int,
        texts: Sequence[Text],
        badges: Sequence[Badge],
        dots: Sequence[Dots] = (),
    ) -> bytes:
        """foxglove ImageAnnotations: texts, badges as filled LINE_LOOP points, and dots as
        POINTS."""


class _RosVisualEncoder(RosBuilder, VisualEncoder):
    """MarkerArray and foxglove_msgs/ImageAnnotations, with rosbags' (de)serializers."""

    store: ClassVar[Stores]
    ros_version: ClassVar[int]

    def __init__(self) -> None:
        self.typestore = get_typestore(self.store)
        types: dict[str, Any] = {}
        for name in (*FOXGLOVE_MSGS, "ImageAnnotations"):
            text = read_schema(f"ros{self.ros_version}/foxglove_msgs/{name}.msg")
            types.update(get_types_from_msg(text, f"foxglove_msgs/msg/{name}"))
        self.typestore.register(types)

    def default(self, typename: str) -> dict[str, Any]:
        """A message of `typename` with every field zero, empty or false (plain form)."""
        return {name: self._default(desc) for name, desc in self.typestore.fielddefs[typename][1]}

    def _default(self, desc: Any) -> Any:
        nodetype, detail = desc
        if nodetype == Nodetype.NAME:
            if detail == "builtin_interfaces/msg/Time":
                return {"sec": 0, "nsec": 0}
            return self.default(detail)
        if nodetype == Nodetype.ARRAY:
            return [self._default(detail[0])] * detail[1]
        if nodetype == Nodetype.SEQUENCE:
            return []
        return {"string": ""}.get(detail[0], False if detail[0] == "bool" else 0)

    def _value(self, desc: Any, value: Any) -> Any:
        if desc == (Nodetype.NAME, "builtin_interfaces/msg/Duration"):
            return self.typestore.types[desc[1]](sec=value["sec"], nanosec=value["nanosec"])
        return super()._value(desc, value)

    def _schema(self, typename: str) -> SchemaInfo:
        text, md5 = self.typestore.generate_msgdef(typename, ros_version=self.ros_version)
        name = typename if self.ros_version == 2 else typename.replace("/msg/", "/")
        metadata = {"md5sum": md5} if self.ros_version == 1 else {}
        return SchemaInfo(name, f"ros{self.ros_version}msg", text.encode(), metadata)

    def scene_schema(self) -> SchemaInfo:
        return self._schema(MARKER_ARRAY)

    def annotations_schema(self) -> SchemaInfo:
        return self._schema(IMAGE_ANNOTATIONS)

    def pose_schema(self) -> SchemaInfo:
        return self._schema(POSE_STAMPED)

    def pose(self, frame_id: str, time_ns: int, position: Point3, orientation: Quaternion) -> bytes:
        types = self.typestore.types
        message = ros_pose_stamped(
            types, self.ros_version, frame_id, time_ns, position, orientation
        )
        if self.ros_version == 2:
            return bytes(self.typestore.serialize_cdr(message, POSE_STAMPED))
        return bytes(self.typestore.serialize_ros1(message, POSE_STAMPED))

    def scene(self, frame_id: str, time_ns: int, lines: Sequence[Lines]) -> bytes:
        markers = [self._marker(frame_id, time_ns, item) for item in lines]
        return self._serialize(MARKER_ARRAY, {"markers": markers})

    def deletion(self, frame_id: str, time_ns: int, namespace: str, number: int) -> bytes:
        marker = self._named_marker(frame_id, time_ns, namespace, number)
        marker["action"] = _ROS_MARKER_DELETE
        return self._serialize(MARKER_ARRAY, {"markers": [marker]})

    def _named_marker(
        self, frame_id: str, time_ns: int, namespace: str, number: int
    ) -> dict[str, Any]:
        marker = self.default("visualization_msgs/msg/Marker")
        marker["header"] = {**marker["header"], "stamp": time_dict(time_ns), "frame_id": frame_id}
        marker.update(ns=namespace, id=number)
        marker["pose"]["orientation"]["w"] = 1.0
        return marker

    def _marker(self, frame_id: str, time_ns: int, lines: Lines) -> dict[str, Any]:
        marker = self._named_marker(frame_id, time_ns, lines.namespace, lines.number)
        marker["type"] = _ROS_MARKER_TYPES[lines.kind]
        marker["scale"]["x"] = lines.thickness_m  # a line's width
        marker["color"] = dict(zip("rgba", lines.color, strict=True))
        marker["points"] = [{"x": x, "y": y, "z": z} for x, y, z in lines.points]
        return marker

    def annotations(
        self,
        time_ns: int,
        texts: Sequence[Text],
        badges: Sequence[Badge],
        dots: Sequence[Dots] = (),
    ) -> bytes:
        return self._serialize(IMAGE_ANNOTATIONS, _annotations(time_ns, texts, badges, dots))

    def _serialize(self, typename: str, message: dict[str, Any]) -> bytes:
        built = self.build(typename, message)
        if self.ros_version == 2:
            return bytes(self.typestore.serialize_cdr(built, typename))
        return bytes(self.typestore.serialize_ros1(built, typename))


class Ros2VisualEncoder(_RosVisualEncoder):
    message_encoding = "cdr"
    ros_version = 2
    store = Stores.ROS2_HUMBLE


class Ros1VisualEncoder(_RosVisualEncoder):
    message_encoding = "ros1"
    ros_version = 1
    store = Stores.ROS1_NOETIC


class JsonVisualEncoder(VisualEncoder):
    """foxglove.SceneUpdate and foxglove.ImageAnnotations as JSON (schemas/json)."""

    message_encoding = "json"

    def _schema(self, name: str) -> SchemaInfo:
        return SchemaInfo(name, "jsonschema", read_schema(f"json/{name}.json").encode(), {})

    def scene_schema(self) -> SchemaInfo:
        return self._schema("foxglove.SceneUpdate")

    def annotations_schema(self) -> SchemaInfo:
        return self._schema("foxglove.ImageAnnotations")

    def pose_schema(self) -> SchemaInfo:
        return self._schema("foxglove.PoseInFrame")

    def pose(self, frame_id: str, time_ns: int, position: Point3, orientation: Quaternion) -> bytes:
        pose = json_pose(position, orientation)
        return json_message({"timestamp": time_dict(time_ns), "frame_id": frame_id, "pose": pose})

    def scene(self, frame_id: str, time_ns: int, lines: Sequence[Lines]) -> bytes:
        entities = [_entity(frame_id, time_ns, item) for item in lines]
        return json_message({"deletions": [], "entities": entities})

    def deletion(self, frame_id: str, time_ns: int, namespace: str, number: int) -> bytes:
        # Entities stamped no later than the deletion's timestamp go.
        deletion = {
            "timestamp": time_dict(time_ns),
            "type": _SCENE_MATCHING_ID,
            "id": _entity_id(namespace, number),
        }
        return json_message({"deletions": [deletion], "entities": []})

    def annotations(
        self,
        time_ns: int,
        texts: Sequence[Text],
        badges: Sequence[Badge],
        dots: Sequence[Dots] = (),
    ) -> bytes:
        return json_message(_annotations(time_ns, texts, badges, dots))


def _entity_id(namespace: str, number: int) -> str:
    return f"{namespace}/{number}"


def _entity(frame_id: str, time_ns: int, lines: Lines) -> dict[str, Any]:
    primitive = {
        "type": _SCENE_LINE_TYPES[lines.kind],
        "pose": {"position": _xyz((0, 0, 0)), "orientation": {"x": 0, "y": 0, "z": 0, "w": 1}},
        "thickness": lines.thickness_m,
        "scale_invariant": False,
        "points": [_xyz(p) for p in lines.points],
        "color": dict(zip("rgba", lines.color, strict=True)),
        "colors": [],
        "indices": [],
    }
    empty: dict[str, list[Any]] = {k: [] for k in ("arrows", "cubes", "spheres", "cylinders")}
    rest: dict[str, list[Any]] = {k: [] for k in ("triangles", "texts", "models")}
    return {
        "timestamp": time_dict(time_ns),
        "frame_id": frame_id,
        "id": _entity_id(lines.namespace, lines.number),
        "lifetime": {"sec": 0, "nsec": 0},  # forever
        "frame_locked": False,
        "metadata": [],
        **empty,
        "lines": [primitive],
        **rest,
    }


def _xyz(point: Iterable[float]) -> dict[str, float]:
    return dict(zip("xyz", (float(v) for v in point), strict=True))


def json_pose(position: Iterable[float], orientation: Iterable[float]) -> dict[str, Any]:
    """A foxglove.Pose as JSON: position x, y, z and orientation x, y, z, w."""
    xyzw = dict(zip("xyzw", (float(v) for v in orientation), strict=True))
    return {"position": _xyz(position), "orientation": xyzw}


def ros_header(types: Any, ros_version: int, frame_id: str, time_ns: int) -> Any:
    """A std_msgs/Header of `types` (a rosbags typestore's), with seq 0 in ROS 1."""
    sec, nanosec = divmod(time_ns, 1_000_000_000)
    fields: dict[str, Any] = {"stamp": types[TIME](sec=sec, nanosec=nanosec)}
    if ros_version == 1:
        fields["seq"] = 0
    return types["std_msgs/msg/Header"](frame_id=frame_id, **fields)


def ros_pose_stamped(
    types: Any,
    ros_version: int,
    frame_id: str,
    time_ns: int,
    position: Iterable[float],
    orientation: Iterable[float],
) -> Any:
    """A geometry_msgs/PoseStamped of `types`, built directly, not by the generic builder: the
    current pose is one at every camera frame, and walking the definition cost three times
    what the rest of the pose costs."""
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](*(float(v) for v in position)),
        orientation=types["geometry_msgs/msg/Quaternion"](*(float(v) for v in orientation)),
    )
    header = ros_header(types, ros_version, frame_id, time_ns)
    return types[POSE_STAMPED](header=header, pose=pose)


def _annotations(
    time_ns: int, texts: Sequence[Text], badges: Sequence[Badge], dots: Sequence[Dots]
) -> dict[str, Any]:
    points = [_badge(time_ns, badge) for badge in badges]
    points += [_dots(time_ns, item) for item in dots if item.points]
    return {"circles": [], "points": points, "texts": [_text(time_ns, t) for t in texts]}


def _dots(time_ns: int, dots: Dots) -> dict[str, Any]:
    # POINTS are painted in outline_color (Foxglove falls back to fill_color): both set.
    color = dict(zip("rgba", dots.color, strict=True))
    return {
        "timestamp": time_dict(time_ns),
        "type": POINTS,
        "points": [{"x": x, "y": y} for x, y in dots.points],
        "outline_color": color,
        "outline_colors": [],
        "fill_color": color,
        "thickness": dots.size,  # a point's radius in image pixels (Foxglove's Image panel)
    }


def _badge(time_ns: int, badge: Badge) -> dict[str, Any]:
    x, y, size = badge.x, badge.y, badge.size
    corners = [(x, y), (x + size, y), (x + size, y + size), (x, y + size)]
    color = dict(zip("rgba", badge.color, strict=True))
    return {
        "timestamp": time_dict(time_ns),
        "type": LINE_LOOP_POINTS,
        "points": [{"x": px, "y": py} for px, py in corners],
        "outline_color": color,
        "outline_colors": [],
        "fill_color": color,
        "thickness": 2.0,
    }


def _text(time_ns: int, text: Text) -> dict[str, Any]:
    return {
        "timestamp": time_dict(time_ns),
        "position": {"x": text.x, "y": text.y},
        "text": text.text,
        "font_size": text.font_size,
        "text_color": dict(zip("rgba", text.color, strict=True)),
        "background_color": dict(zip("rgba", text.background, strict=True)),
    }


def json_message(message: dict[str, Any]) -> bytes:
    """A JSON message as our JSON channels hold it: compact, NaN refused."""
    return json.dumps(message, allow_nan=False, separators=(",", ":")).encode()


def visual_encoder_for_profile(profile: str) -> VisualEncoder:
    """The ROS 2 / ROS 1 encoder for those profiles, JSON for every other (as `encoders`)."""
    if profile == "ros2":
        return Ros2VisualEncoder()
    if profile == "ros1":
        return Ros1VisualEncoder()
    return JsonVisualEncoder()
