"""An MCAP copied record for record, plus one pose topic (the `optimize` command's output).

The pose messages use the type a viewer draws in the file's profile, as the odometry:

* ROS 2 profile: `geometry_msgs/msg/PoseStamped` (CDR);
* ROS 1 profile: `geometry_msgs/PoseStamped` (ROS 1 serialization, md5sum in the channel);
* any other profile (Foxglove): `foxglove.PoseInFrame`, protobuf when the odometry channel is
  protobuf (the `protobuf` extra, which reading such a log already needs), else JSON.

Every record of the input (schemas, channels, messages, attachments, metadata) is copied
unchanged, except an earlier channel of the same topic (a log optimized twice), which the new
poses replace. The output appears atomically (`atomic`).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.writer import Writer
from rosbags.typesys import Stores, get_typestore

from ..annotations.records import time_dict
from ..annotations.schema_files import read_schema
from ..errors import SourceError
from ..sources.formats import plan_copy
from ..sources.mcap_copy import input_records
from .atomic import atomic_output
from .mcap_writer import LIBRARY, refuse_same_file
from .output_format import COMPRESSIONS, OutputFormat

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

FoxgloveEncoding = Literal["protobuf", "json"]
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_IN_FRAME = "foxglove.PoseInFrame"


@dataclass(frozen=True)
class PoseStream:
    """Poses to add as one topic: stamped at `stamps_ns`, logged at `log_times_ns`."""

    topic: str
    frame_id: str
    log_times_ns: I64
    stamps_ns: I64  # the header stamp (PoseInFrame: timestamp) of each pose
    positions: F64  # (N, 3)
    quaternions_xyzw: F64  # (N, 4)
    foxglove_encoding: FoxgloveEncoding = "json"  # for profiles other than ros1 / ros2


@dataclass(frozen=True)
class _PoseSchema:
    name: str
    encoding: str
    data: bytes
    message_encoding: str
    channel_metadata: dict[str, str]


class _PoseEncoder:
    """The schema and message bytes of a pose in one profile."""

    def __init__(self, profile: str, foxglove_encoding: FoxgloveEncoding) -> None:
        self.profile = profile
        self.foxglove_encoding = foxglove_encoding
        self.typestore = None
        if profile in ("ros1", "ros2"):
            store = Stores.ROS1_NOETIC if profile == "ros1" else Stores.ROS2_HUMBLE
            self.typestore = get_typestore(store)

    def schema(self) -> _PoseSchema:
        if self.typestore is not None:
            version = 1 if self.profile == "ros1" else 2
            text, md5 = self.typestore.generate_msgdef(POSE_STAMPED, ros_version=version)
            if version == 1:
                return _PoseSchema(
                    "geometry_msgs/PoseStamped", "ros1msg", text.encode(), "ros1", {"md5sum": md5}
                )
            return _PoseSchema(POSE_STAMPED, "ros2msg", text.encode(), "cdr", {})
        if self.foxglove_encoding == "protobuf":
            from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
            from mcap_protobuf.schema import build_file_descriptor_set

            data = build_file_descriptor_set(PoseInFrame).SerializeToString()
            return _PoseSchema(POSE_IN_FRAME, "protobuf", data, "protobuf", {})
        data = read_schema(f"json/{POSE_IN_FRAME}.json").encode()
        return _PoseSchema(POSE_IN_FRAME, "jsonschema", data, "json", {})

    def encode(self, frame_id: str, stamp_ns: int, position: F64, quaternion: F64) -> bytes:
        xyz = dict(zip("xyz", (float(v) for v in position), strict=True))
        xyzw = dict(zip("xyzw", (float(v) for v in quaternion), strict=True))
        if self.typestore is not None:
            return self._ros(frame_id, stamp_ns, xyz, xyzw)
        if self.foxglove_encoding == "protobuf":
            return self._protobuf(frame_id, stamp_ns, xyz, xyzw)
        message = {
            "timestamp": time_dict(stamp_ns),
            "frame_id": frame_id,
            "pose": {"position": xyz, "orientation": xyzw},
        }
        return json.dumps(message, allow_nan=False, separators=(",", ":")).encode()

    def _ros(
        self, frame_id: str, stamp_ns: int, xyz: dict[str, float], xyzw: dict[str, float]
    ) -> bytes:
        store: Any = self.typestore
        types = store.types
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        header_fields: dict[str, Any] = {
            "stamp": types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
            "frame_id": frame_id,
        }
        if self.profile == "ros1":
            header_fields["seq"] = 0
        message = types[POSE_STAMPED](
            header=types["std_msgs/msg/Header"](**header_fields),
            pose=types["geometry_msgs/msg/Pose"](
                position=types["geometry_msgs/msg/Point"](**xyz),
                orientation=types["geometry_msgs/msg/Quaternion"](**xyzw),
            ),
        )
        if self.profile == "ros1":
            return bytes(store.serialize_ros1(message, POSE_STAMPED))
        return bytes(store.serialize_cdr(message, POSE_STAMPED))

    @staticmethod
    def _protobuf(
        frame_id: str, stamp_ns: int, xyz: dict[str, float], xyzw: dict[str, float]
    ) -> bytes:
        from foxglove_schemas_protobuf.Pose_pb2 import Pose
        from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
        from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
        from foxglove_schemas_protobuf.Vector3_pb2 import Vector3

        message = PoseInFrame(
            frame_id=frame_id,
            pose=Pose(position=Vector3(**xyz), orientation=Quaternion(**xyzw)),
        )
        seconds, nanos = divmod(stamp_ns, 1_000_000_000)
        message.timestamp.seconds, message.timestamp.nanos = seconds, nanos
        data: bytes = message.SerializeToString()
        return data


@dataclass(frozen=True)
class PoseWriteSummary:
    """What `write_with_poses` wrote."""

    output_path: Path
    profile: str
    copied_messages: int
    pose_messages: int
    replaced_topic: bool  # the input had the topic already; its messages were left out


class _Copier:
    """Copies an MCAP's records into `writer`, the poses interleaved by log time."""

    def __init__(self, writer: Writer, poses: PoseStream, encoder: _PoseEncoder) -> None:
        self.writer, self.poses, self.encoder = writer, poses, encoder
        self.schemas: dict[int, Schema] = {}
        self.schema_ids: dict[int, int] = {}
        self.channel_ids: dict[int, int] = {}
        self.dropped: set[int] = set()  # input channels of our topic
        self.pose_channel: int | None = None
        # In log-time order, whatever order the frames' log times came in.
        self.order = np.argsort(poses.log_times_ns, kind="stable")
        self.next_pose = 0
        self.copied = 0

    def copy(self, path: Path) -> None:
        for record in input_records(path):
            self._record(record, path)
        self.write_poses_until(None)
        for schema_id, schema in self.schemas.items():  # schemas no channel used
            self._schema(schema_id, schema)

    def write_poses_until(self, log_time_ns: int | None) -> None:
        poses = self.poses
        while self.next_pose < len(self.order):
            k = int(self.order[self.next_pose])
            log_time = int(poses.log_times_ns[k])
            if log_time_ns is not None and log_time > log_time_ns:
                return
            if self.pose_channel is None:
                self.pose_channel = self._register_pose_channel()
            data = self.encoder.encode(
                poses.frame_id,
                int(poses.stamps_ns[k]),
                poses.positions[k],
                poses.quaternions_xyzw[k],
            )
            sequence = self.next_pose & 0xFFFFFFFF
            self.writer.add_message(self.pose_channel, log_time, data, log_time, sequence)
            self.next_pose += 1

    def _register_pose_channel(self) -> int:
        schema = self.encoder.schema()
        schema_id = self.writer.register_schema(schema.name, schema.encoding, schema.data)
        return self.writer.register_channel(
            self.poses.topic, schema.message_encoding, schema_id, schema.channel_metadata
        )

    def _record(self, record: object, path: Path) -> None:
        if isinstance(record, Schema):
            self.schemas.setdefault(record.id, record)
        elif isinstance(record, Channel):
            self._channel(record, path)
        elif isinstance(record, Message):
            self._message(record, path)
        elif isinstance(record, Attachment):
            self.writer.add_attachment(
                record.create_time, record.log_time, record.name, record.media_type, record.data
            )
        elif isinstance(record, Metadata):
            self.writer.add_metadata(record.name, record.metadata)

    def _schema(self, schema_id: int, schema: Schema) -> int:
        if schema_id not in self.schema_ids:
            self.schema_ids[schema_id] = self.writer.register_schema(
                schema.name, schema.encoding, schema.data
            )
        return self.schema_ids[schema_id]

    def _channel(self, channel: Channel, path: Path) -> None:
        if channel.id in self.channel_ids or channel.id in self.dropped:
            return  # repeated in the summary section
        if channel.topic == self.poses.topic:
            self.dropped.add(channel.id)
            return
        schema_id = 0
        if channel.schema_id != 0:
            schema = self.schemas.get(channel.schema_id)
            if schema is None:
                raise SourceError(
                    f"{path}: a channel refers to the unknown schema {channel.schema_id}"
                )
            schema_id = self._schema(channel.schema_id, schema)
        self.channel_ids[channel.id] = self.writer.register_channel(
            channel.topic, channel.message_encoding, schema_id, dict(channel.metadata)
        )

    def _message(self, message: Message, path: Path) -> None:
        channel_id = self.channel_ids.get(message.channel_id)
        if channel_id is None:
            if message.channel_id in self.dropped:
                return
            raise SourceError(f"{path}: a message refers to the unknown channel")
        self.write_poses_until(message.log_time)
        self.writer.add_message(
            channel_id, message.log_time, message.data, message.publish_time, message.sequence
        )
        self.copied += 1


def write_with_poses(
    input_path: str | os.PathLike[str],
    output_path: str | os.PathLike[str],
    poses: PoseStream,
    output_format: OutputFormat | None = None,
) -> PoseWriteSummary:
    """Writes `output_path`: every record of the MCAP at `input_path` plus `poses` as one
    topic in the input's profile (module docstring).

    Raises SourceError when the input is not a readable MCAP, OutputError when the output
    cannot be written or would overwrite the input.
    """
    source, output = Path(input_path), Path(output_path)
    log = plan_copy(source)
    if log.kind != "mcap":
        raise SourceError(f"{source}: not an MCAP file (an annotated log is one)")
    refuse_same_file(source, output)
    refuse_same_file(log.path, output)
    output_format = output_format or OutputFormat()
    encoder = _PoseEncoder(log.profile, poses.foxglove_encoding)
    with atomic_output(output) as stream:
        writer = Writer(
            stream,
            chunk_size=output_format.chunk_size,
            compression=COMPRESSIONS[output_format.compression],
        )
        writer.start(profile=log.profile, library=LIBRARY)
        copier = _Copier(writer, poses, encoder)
        copier.copy(log.path)
        writer.finish()  # type: ignore[no-untyped-call]  # mcap leaves it unannotated
    return PoseWriteSummary(
        output, log.profile, copier.copied, copier.next_pose, bool(copier.dropped)
    )
