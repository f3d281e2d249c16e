"""An MCAP copied record for record, plus one pose topic and whole paths (the `optimize`
command's output).

The messages use the types a viewer draws in the file's profile, as the odometry:

* ROS 2 profile: `geometry_msgs/msg/PoseStamped` per pose, `nav_msgs/msg/Path` per path (CDR);
* ROS 1 profile: `geometry_msgs/PoseStamped`, `nav_msgs/Path` (ROS 1 serialization, md5sum in
  the channel);
* any other profile (Foxglove): `foxglove.PoseInFrame`, `foxglove.PosesInFrame`, protobuf when
  the odometry channel is protobuf (the `protobuf` extra, which reading such a log already
  needs), else JSON.

A pose topic carries one pose per message, which a viewer shows as the current pose only; a
path is the whole trajectory in one message, written before the log's first message so that a
viewer seeking anywhere draws all of it.

Every record of the input (schemas, channels, messages, attachments, metadata) is copied
unchanged, except earlier channels of the topics written (a log optimized twice), which the
new messages replace. The output appears atomically (`atomic`).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
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
from .visual_encoders import json_message, json_pose, ros_header, ros_pose_stamped

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

FoxgloveEncoding = Literal["protobuf", "json"]
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
PATH = "nav_msgs/msg/Path"
POSE_IN_FRAME = "foxglove.PoseInFrame"
POSES_IN_FRAME = "foxglove.PosesInFrame"


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
class PathMessage:
    """A whole trajectory as one message on `topic`, in the pose stream's encoding; each pose
    stamped at `stamps_ns`, the message at the last of them."""

    topic: str
    frame_id: str
    stamps_ns: I64
    positions: F64  # (N, 3)
    quaternions_xyzw: F64  # (N, 4)


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
        """The schema of one pose a message."""
        return self._schema(POSE_STAMPED, POSE_IN_FRAME)

    def path_schema(self) -> _PoseSchema:
        """The schema of a whole path a message."""
        return self._schema(PATH, POSES_IN_FRAME)

    def _schema(self, ros_type: str, foxglove_type: str) -> _PoseSchema:
        if self.typestore is not None:
            version = 1 if self.profile == "ros1" else 2
            text, md5 = self.typestore.generate_msgdef(ros_type, ros_version=version)
            if version == 1:
                name = ros_type.replace("/msg/", "/")
                return _PoseSchema(name, "ros1msg", text.encode(), "ros1", {"md5sum": md5})
            return _PoseSchema(ros_type, "ros2msg", text.encode(), "cdr", {})
        if self.foxglove_encoding == "protobuf":
            from mcap_protobuf.schema import build_file_descriptor_set

            message = _protobuf_class(foxglove_type)
            data = build_file_descriptor_set(message).SerializeToString()
            return _PoseSchema(foxglove_type, "protobuf", data, "protobuf", {})
        data = read_schema(f"json/{foxglove_type}.json").encode()
        return _PoseSchema(foxglove_type, "jsonschema", data, "json", {})

    def encode(self, frame_id: str, stamp_ns: int, position: F64, quaternion: F64) -> bytes:
        """One pose as a message."""
        if self.typestore is not None:
            return self._serialize(self._ros_pose(frame_id, stamp_ns, position, quaternion))
        if self.foxglove_encoding == "protobuf":
            from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame

            message = PoseInFrame(frame_id=frame_id, pose=_protobuf_pose(position, quaternion))
            _set_timestamp(message, stamp_ns)
            return bytes(message.SerializeToString())
        pose = {"timestamp": time_dict(stamp_ns), "frame_id": frame_id}
        return json_message({**pose, "pose": json_pose(position, quaternion)})

    def encode_path(self, path: PathMessage) -> bytes:
        """A whole path as one message, stamped at its last pose."""
        stamp_ns = int(path.stamps_ns[-1]) if len(path.stamps_ns) else 0
        poses = zip(path.stamps_ns, path.positions, path.quaternions_xyzw, strict=True)
        if self.typestore is not None:
            types = self.typestore.types
            stamped = [self._ros_pose(path.frame_id, int(t), p, q) for t, p, q in poses]
            header = self._header(path.frame_id, stamp_ns)
            return self._serialize(types[PATH](header=header, poses=stamped), PATH)
        if self.foxglove_encoding == "protobuf":
            from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame

            message = PosesInFrame(
                frame_id=path.frame_id, poses=[_protobuf_pose(p, q) for _, p, q in poses]
            )
            _set_timestamp(message, stamp_ns)
            return bytes(message.SerializeToString())
        document = {
            "timestamp": time_dict(stamp_ns),
            "frame_id": path.frame_id,
            "poses": [json_pose(p, q) for _, p, q in poses],
        }
        return json_message(document)

    def _header(self, frame_id: str, stamp_ns: int) -> Any:
        types = self.typestore.types  # type: ignore[union-attr]  # ROS profiles only
        return ros_header(types, self._ros_version, frame_id, stamp_ns)

    def _ros_pose(self, frame_id: str, stamp_ns: int, position: F64, quaternion: F64) -> Any:
        types = self.typestore.types  # type: ignore[union-attr]  # ROS profiles only
        return ros_pose_stamped(types, self._ros_version, frame_id, stamp_ns, position, quaternion)

    @property
    def _ros_version(self) -> int:
        return 1 if self.profile == "ros1" else 2

    def _serialize(self, message: Any, typename: str = POSE_STAMPED) -> bytes:
        store: Any = self.typestore
        if self.profile == "ros1":
            return bytes(store.serialize_ros1(message, typename))
        return bytes(store.serialize_cdr(message, typename))


def _protobuf_class(name: str) -> Any:
    """foxglove_schemas_protobuf's class of a Foxglove schema name."""
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
    from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame

    return {POSE_IN_FRAME: PoseInFrame, POSES_IN_FRAME: PosesInFrame}[name]


def _protobuf_pose(position: F64, quaternion: F64) -> Any:
    from foxglove_schemas_protobuf.Pose_pb2 import Pose
    from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
    from foxglove_schemas_protobuf.Vector3_pb2 import Vector3

    pose = json_pose(position, quaternion)
    return Pose(position=Vector3(**pose["position"]), orientation=Quaternion(**pose["orientation"]))


def _set_timestamp(message: Any, stamp_ns: int) -> None:
    message.timestamp.seconds, message.timestamp.nanos = divmod(stamp_ns, 1_000_000_000)


@dataclass(frozen=True)
class PoseWriteSummary:
    """What `write_with_poses` wrote."""

    output_path: Path
    profile: str
    copied_messages: int
    pose_messages: int
    replaced_topic: bool  # the input had a topic written already; its messages were left out
    path_messages: int = 0


class _Copier:
    """Copies an MCAP's records into `writer`, the poses interleaved by log time and the paths
    before the first message."""

    def __init__(
        self,
        writer: Writer,
        poses: PoseStream,
        encoder: _PoseEncoder,
        paths: Sequence[PathMessage] = (),
    ) -> None:
        self.writer, self.poses, self.encoder, self.paths = writer, poses, encoder, paths
        self.topics = {poses.topic, *(path.topic for path in paths)}
        self.paths_written = False
        self.schemas: dict[int, Schema] = {}
        self.schema_ids: dict[int, int] = {}
        self.channel_ids: dict[int, int] = {}
        self.dropped: set[int] = set()  # input channels of the topics written
        self.pose_channel: int | None = None
        # In log-time order, whatever order the frames' log times came in.
        self.order = np.argsort(poses.log_times_ns, kind="stable")
        self.next_pose = 0
        self.copied = 0

    def copy(self, path: Path) -> None:
        for record in input_records(path):
            self._record(record, path)
        self.write_paths(None)
        self.write_poses_until(None)
        for schema_id, schema in self.schemas.items():  # schemas no channel used
            self._schema(schema_id, schema)

    def write_paths(self, log_time_ns: int | None) -> None:
        """The paths, once, before the first message (at `log_time_ns`, the first message's,
        or the first pose's when it comes earlier): a viewer seeking anywhere has them."""
        if self.paths_written:
            return
        self.paths_written = True
        if self.next_pose < len(self.order):
            first_pose = int(self.poses.log_times_ns[self.order[self.next_pose]])
            log_time_ns = first_pose if log_time_ns is None else min(log_time_ns, first_pose)
        if not self.paths:
            return
        schema = self.encoder.path_schema()
        schema_id = self.writer.register_schema(schema.name, schema.encoding, schema.data)
        time = log_time_ns or 0
        for path in self.paths:
            channel = self.writer.register_channel(
                path.topic, schema.message_encoding, schema_id, schema.channel_metadata
            )
            self.writer.add_message(channel, time, self.encoder.encode_path(path), time, 0)

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
        if channel.topic in self.topics:
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
        self.write_paths(message.log_time)
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
    paths: Sequence[PathMessage] = (),
) -> PoseWriteSummary:
    """Writes `output_path`: every record of the MCAP at `input_path` plus `poses` as one
    topic and each of `paths` as one message on its topic, in the input's profile (module
    docstring).

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
        copier = _Copier(writer, poses, encoder, paths)
        copier.copy(log.path)
        writer.finish()  # type: ignore[no-untyped-call]  # mcap leaves it unannotated
    return PoseWriteSummary(
        output, log.profile, copier.copied, copier.next_pose, bool(copier.dropped), len(paths)
    )
