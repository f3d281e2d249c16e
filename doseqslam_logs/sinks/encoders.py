"""Our message types in each output encoding, one encoder per MCAP profile.

Every encoder reads its definitions from `schemas/` (the one source of truth) and knows the
schema encoding, schema name and data, channel metadata and message bytes of our types. A new
profile is one new `MessageEncoder` subclass plus one entry in `ENCODERS`.
"""

from __future__ import annotations

import functools
import json
import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

import numpy as np
from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from ..annotations.records import MESSAGE_TYPES, MessageType
from ..annotations.schema_files import read_schema

ROS_PACKAGE = "doseqslam_msgs"
TIME_TYPE = "builtin_interfaces/msg/Time"
# The separator ROS tools put between concatenated message definitions.
MSGDEF_SEPARATOR = "=" * 80 + "\n"
_NUMPY_TYPES: dict[str, type[np.generic]] = {
    "bool": np.bool_,
    "byte": np.uint8,
    "char": np.uint8,
    "int8": np.int8,
    "uint8": np.uint8,
    "int16": np.int16,
    "uint16": np.uint16,
    "int32": np.int32,
    "uint32": np.uint32,
    "int64": np.int64,
    "uint64": np.uint64,
    "float32": np.float32,
    "float64": np.float64,
}


class MessageEncoder(ABC):
    """How our message types are written in files of one MCAP profile."""

    profile: ClassVar[str]  # the MCAP header profile this encoder is for
    schema_encoding: ClassVar[str]
    message_encoding: ClassVar[str]

    @abstractmethod
    def schema_name(self, message_type: MessageType) -> str:
        """The schema record's name, e.g. `doseqslam_msgs/msg/LoopClosure`."""

    @abstractmethod
    def schema_data(self, message_type: MessageType) -> bytes:
        """The schema record's data: the definition from `schemas/`."""

    def channel_metadata(self, message_type: MessageType) -> dict[str, str]:
        """The channel record's metadata (none unless the profile asks for some)."""
        return {}

    @abstractmethod
    def encode(self, message_type: MessageType, fields: Mapping[str, Any]) -> bytes:
        """The message bytes. Raises ValueError when `fields` are not the schema's fields."""


def check_fields(type_name: str, expected: list[str], fields: Mapping[str, Any]) -> None:
    """Raises ValueError unless `fields` has exactly the schema's field names."""
    missing = [name for name in expected if name not in fields]
    extra = sorted(set(fields) - set(expected))
    if missing or extra:
        raise ValueError(f"{type_name}: missing fields {missing}, unknown fields {extra}")


# A type's field names, (name, conversion or None) per field, and its class (`RosBuilder._plan`).
_Plan = tuple[set[str], list[tuple[str, Callable[[Any], Any] | None]], Callable[..., object]]


class RosBuilder:
    """Rosbags message objects from plain message dicts, for the types of `typestore`."""

    typestore: Typestore

    def build(self, typename: str, fields: Mapping[str, Any]) -> object:
        """The rosbags message object for a plain message dict.

        Raises ValueError when the dict's fields differ from the definition's.
        """
        names, steps, make = self._plan(typename)
        if fields.keys() != names:
            check_fields(typename, [name for name, _ in steps], fields)
        values = {
            name: fields[name] if convert is None else convert(fields[name])
            for name, convert in steps
        }
        return make(**values)

    def _plan(self, typename: str) -> _Plan:
        """The type's field names, each field's conversion (None: a base value, passed as it
        is) and its class, worked out once per type: our records and the visualization's
        messages are built by the ten thousand."""
        plans: dict[str, _Plan] = self.__dict__.setdefault("_plans", {})
        if typename not in plans:
            fielddefs = self.typestore.fielddefs[typename][1]
            steps: list[tuple[str, Callable[[Any], Any] | None]] = [
                (name, None if desc[0] == Nodetype.BASE else functools.partial(self._value, desc))
                for name, desc in fielddefs
            ]
            plans[typename] = {name for name, _ in fielddefs}, steps, self.typestore.types[typename]
        return plans[typename]

    def _value(self, desc: Any, value: Any) -> Any:
        nodetype, detail = desc
        if nodetype == Nodetype.NAME:
            if detail == TIME_TYPE:  # our dicts spell it {"sec", "nsec"} for every encoding
                return self.typestore.types[TIME_TYPE](sec=value["sec"], nanosec=value["nsec"])
            return self.build(detail, value)
        if nodetype in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            item_desc = detail[0]
            if item_desc[0] == Nodetype.BASE and item_desc[1][0] in _NUMPY_TYPES:
                # rosbags serializes primitive arrays from numpy arrays only.
                return np.asarray(value, dtype=_NUMPY_TYPES[item_desc[1][0]])
            if item_desc[0] == Nodetype.NAME and self._is_flat(item_desc[1]):
                return self._flat_items(item_desc[1], value)
            return [self._value(item_desc, item) for item in value]
        return value

    def _is_flat(self, typename: str) -> bool:
        """Whether a type's fields are all of base types (points, colours), so that its
        dicts map onto the constructor's arguments as they are. The builtin times are not:
        our dicts spell their fields otherwise."""
        if typename.startswith("builtin_interfaces/"):
            return False
        return all(convert is None for _, convert in self._plan(typename)[1])

    def _flat_items(self, typename: str, items: Any) -> list[object]:
        """Sequences of a flat type (the thousands of points of the loop lines and inlier
        dots) built straight from their dicts: the constructor checks the field names, the
        values pass unchanged as `build` passes base values, at a tenth of its cost."""
        make = self.typestore.types[typename]
        try:
            return [make(**item) for item in items]
        except TypeError:
            for item in items:  # the one that failed, with `build`'s error
                self.build(typename, item)
            raise


class _RosEncoder(RosBuilder, MessageEncoder):
    """Shared by ROS 1 and ROS 2: rosbags' typestore, filled from our .msg files."""

    ros_version: ClassVar[int]

    def __init__(self) -> None:
        self.typestore: Typestore = get_typestore(Stores.EMPTY)  # only builtin Time, Duration
        self.msg_texts = {t.name: read_schema(self._msg_file(t)) for t in MESSAGE_TYPES}
        types = {}
        for message_type in MESSAGE_TYPES:
            text = self.msg_texts[message_type.name]
            types.update(get_types_from_msg(text, self.typename(message_type)))
        self.typestore.register(types)

    def _msg_file(self, message_type: MessageType) -> str:
        return f"ros{self.ros_version}/{message_type.name}.msg"

    @staticmethod
    def typename(message_type: MessageType) -> str:
        """The name rosbags knows the type by (always the ROS 2 form)."""
        return f"{ROS_PACKAGE}/msg/{message_type.name}"


class Ros2Encoder(_RosEncoder):
    """ROS 2: `ros2msg` schemas and CDR messages, as rosbag2 and mcap_ros2 expect."""

    profile = "ros2"
    schema_encoding = "ros2msg"
    message_encoding = "cdr"
    ros_version = 2

    def schema_name(self, message_type: MessageType) -> str:
        return self.typename(message_type)

    def schema_data(self, message_type: MessageType) -> bytes:
        """Our .msg text, then the definitions it depends on (builtin_interfaces/Time).

        Dependencies follow in the `===...` / `MSG: pkg/Type` form of rosbag2, which
        mcap_ros2 and rosbags both parse.
        """
        text = self.msg_texts[message_type.name]
        generated, _ = self.typestore.generate_msgdef(self.typename(message_type), ros_version=2)
        _, separator, dependencies = generated.partition(MSGDEF_SEPARATOR)
        if not text.endswith("\n"):
            text += "\n"
        return (text + separator + dependencies).encode()

    def encode(self, message_type: MessageType, fields: Mapping[str, Any]) -> bytes:
        typename = self.typename(message_type)
        return bytes(self.typestore.serialize_cdr(self.build(typename, fields), typename))


class Ros1Encoder(_RosEncoder):
    """ROS 1: `ros1msg` schemas and ROS 1 serialization; `time` is a builtin there."""

    profile = "ros1"
    schema_encoding = "ros1msg"
    message_encoding = "ros1"
    ros_version = 1

    def schema_name(self, message_type: MessageType) -> str:
        return f"{ROS_PACKAGE}/{message_type.name}"

    def schema_data(self, message_type: MessageType) -> bytes:
        return self.msg_texts[message_type.name].encode()

    def md5sum(self, message_type: MessageType) -> str:
        """The ROS 1 md5sum of the definition, as rosbag and rospy compute it."""
        _, md5 = self.typestore.generate_msgdef(self.typename(message_type), ros_version=1)
        return md5

    def channel_metadata(self, message_type: MessageType) -> dict[str, str]:
        # ROS 1 consumers (playback, bag conversion) need the md5sum to advertise the type.
        return {"md5sum": self.md5sum(message_type)}

    def encode(self, message_type: MessageType, fields: Mapping[str, Any]) -> bytes:
        typename = self.typename(message_type)
        return bytes(self.typestore.serialize_ros1(self.build(typename, fields), typename))


class JsonEncoder(MessageEncoder):
    """Any other profile (foxglove, none): JSON messages described by a JSON Schema."""

    profile = ""
    schema_encoding = "jsonschema"
    message_encoding = "json"

    def __init__(self) -> None:
        self.texts = {t.name: read_schema(f"json/{t.name}.json") for t in MESSAGE_TYPES}
        self.properties = {
            name: list(json.loads(text)["properties"]) for name, text in self.texts.items()
        }

    def schema_name(self, message_type: MessageType) -> str:
        return f"{ROS_PACKAGE}/msg/{message_type.name}"

    def schema_data(self, message_type: MessageType) -> bytes:
        return self.texts[message_type.name].encode()

    def encode(self, message_type: MessageType, fields: Mapping[str, Any]) -> bytes:
        check_fields(message_type.name, self.properties[message_type.name], fields)
        ordered = without_nan({name: fields[name] for name in self.properties[message_type.name]})
        if not any(_holds_infinity(value) for value in ordered.values()):
            # allow_nan=False: NaN is not JSON; without_nan already left it out.
            return json.dumps(ordered, allow_nan=False, separators=(",", ":")).encode()
        items = (f"{json.dumps(name)}:{_json_value(value)}" for name, value in ordered.items())
        return ("{" + ",".join(items) + "}").encode()


def without_nan(message: Mapping[str, Any]) -> dict[str, Any]:
    """The message without its NaN floats, nor its float arrays that hold one.

    NaN is not JSON, and a `null` would need a second type in the schema, which Foxglove's
    and Lichtblick's JSON-schema parser refuse: the schemas document an absent float as NaN,
    and `records` reads it back so.
    """
    return {key: value for key, value in message.items() if not _holds_nan(value)}


def _holds_nan(value: Any) -> bool:
    """NaN anywhere, or an infinite float outside an array (only a float array, the
    covariance's unconstrained variances, keeps its infinities: `_json_value`)."""
    if isinstance(value, float):
        return not math.isfinite(value)
    if isinstance(value, (list, tuple)):
        return any(isinstance(item, float) and math.isnan(item) for item in value)
    return False


def _holds_infinity(value: Any) -> bool:
    return isinstance(value, (list, tuple)) and any(
        isinstance(item, float) and math.isinf(item) for item in value
    )


def _json_value(value: Any) -> str:
    """A value as compact JSON, an infinite float in an array as the number 1e999: JSON's
    grammar has no infinity, but any exponent, and JSON parsers (Python's json, JavaScript's
    JSON.parse) read 1e999 as infinity; `records` reads it back so."""
    if not _holds_infinity(value):
        return json.dumps(value, allow_nan=False, separators=(",", ":"))
    return "[" + ",".join(_json_float(item) for item in value) + "]"


def _json_float(item: Any) -> str:
    if isinstance(item, float) and math.isinf(item):
        return "1e999" if item > 0 else "-1e999"
    return json.dumps(item, allow_nan=False)


ENCODERS: dict[str, type[MessageEncoder]] = {
    Ros2Encoder.profile: Ros2Encoder,
    Ros1Encoder.profile: Ros1Encoder,
    JsonEncoder.profile: JsonEncoder,
}


def encoder_for_profile(profile: str) -> MessageEncoder:
    """The encoder for files of this MCAP profile; JSON for every profile without its own."""
    return ENCODERS.get(profile, JsonEncoder)()
