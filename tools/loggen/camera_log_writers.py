"""Write a stream of camera frames (plus optional extra topics) into each log container.

One module for every tool that makes logs (`make_sample_logs.py`, `pack_image_folder.py`), so
that the container code exists once:

* ``ros2mcap`` - MCAP, profile ``ros2``, CDR messages with ``ros2msg`` schemas
  (sensor_msgs/msg/CompressedImage or Image, CameraInfo, nav_msgs/msg/Odometry,
  geometry_msgs/msg/PoseStamped);
* ``foxglove`` - MCAP with Foxglove protobuf schemas (foxglove.CompressedImage or RawImage,
  foxglove.CameraCalibration, foxglove.PoseInFrame for odometry and ground truth);
* ``bag`` - ROS 1 bag v2.0 (chunk compression none, bz2 or lz4);
* ``db3`` - ROS 2 bag directory: sqlite3 storage plus metadata.yaml.

An aligned depth image (encoding ``32FC1``, metres, or ``16UC1``, millimetres; REP 118) is an
`ImageFrame` too: it goes to `Topics.depth_image` as sensor_msgs/Image (Foxglove: RawImage),
and `write_camera_info(..., topic=Topics.depth_camera_info)` gives it its CameraInfo.

ROS messages are built and serialized with the rosbags type stores (CDR for ROS 2, ROS 1 wire
format for bags), so the two ROS 2 containers carry byte-identical message payloads.

Every output is byte-deterministic for the same input: the MCAP header's library field is a
fixed string (no versions, no dates), timestamps come only from the caller, and rosbag2's
metadata.yaml holds only message times. The bytes can still change when a compression library
(zstd, lz4, bz2) or sqlite3 itself changes version. Each output is written under a temporary
name in the target folder and renamed into place on `close`, so a reader never sees half a log.
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
from abc import ABC, abstractmethod
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Final, Literal, get_args

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage as FoxCompressedImage
from foxglove_schemas_protobuf.Pose_pb2 import Pose as FoxPose
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage as FoxRawImage
from google.protobuf.message import Message  # type: ignore[import-untyped, unused-ignore]
from google.protobuf.timestamp_pb2 import Timestamp  # type: ignore[import-untyped, unused-ignore]
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_protobuf.schema import register_schema
from rosbags.rosbag1 import Writer as Bag1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Bag2Writer
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

Format = Literal["ros2mcap", "foxglove", "bag", "db3"]
FORMATS: Final[tuple[Format, ...]] = get_args(Format)
BagCompression = Literal["none", "bz2", "lz4"]
McapCompression = Literal["none", "lz4", "zstd"]

# Fixed, version-free writer name: a library upgrade must not change the bytes of a log.
MCAP_LIBRARY: Final = "doseqslam-logs camera_log_writers"

COMPRESSED_FORMATS: Final = ("jpeg", "png")
RAW_ENCODINGS: Final = {"mono8": 1, "rgb8": 3, "bgr8": 3}
# Depth images as ROS RGB-D drivers write them (REP 118): bytes per pixel, little-endian.
DEPTH_ENCODINGS: Final = {"32FC1": 4, "16UC1": 2}
_PIXEL_BYTES: Final = {**RAW_ENCODINGS, **DEPTH_ENCODINGS}

_MCAP_COMPRESSION: Final = {
    "none": CompressionType.NONE,
    "lz4": CompressionType.LZ4,
    "zstd": CompressionType.ZSTD,
}
_BAG_COMPRESSION: Final = {
    "bz2": Bag1Writer.CompressionFormat.BZ2,
    "lz4": Bag1Writer.CompressionFormat.LZ4,
}

# Plausible, fixed covariances: a reader that checks them finds sensible diagonals.
_ODOM_POSE_COV: Final = (0.05, 0.05, 1e6, 1e6, 1e6, 0.01)
_ODOM_TWIST_COV: Final = (0.01, 1e6, 1e6, 1e6, 1e6, 0.005)


# -- what the writers are fed -------------------------------------------------------------------


@dataclass(frozen=True)
class Topics:
    """Topic and frame names; the defaults follow common ROS camera drivers."""

    compressed_image: str = "/camera/image/compressed"
    raw_image: str = "/camera/image_raw"
    camera_info: str = "/camera/camera_info"
    depth_image: str = "/camera/depth/image"
    depth_camera_info: str = "/camera/depth/camera_info"
    odometry: str = "/odom"
    ground_truth: str = "/ground_truth/pose"
    camera_frame: str = "camera"
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    map_frame: str = "map"


@dataclass(frozen=True)
class ImageFrame:
    """One camera image, already encoded.

    `encoding` is "jpeg" or "png" for a compressed image (data = the file bytes), a ROS raw
    encoding ("mono8", "rgb8", "bgr8"; data = rows without padding) for a raw one, or a depth
    encoding ("32FC1", "16UC1"; little-endian rows without padding) for a depth image.
    """

    stamp_ns: int
    data: bytes
    encoding: str
    width: int = 0
    height: int = 0

    @property
    def compressed(self) -> bool:
        return self.encoding in COMPRESSED_FORMATS

    @property
    def depth(self) -> bool:
        return self.encoding in DEPTH_ENCODINGS

    def __post_init__(self) -> None:
        if self.compressed:
            return
        pixel_bytes = _PIXEL_BYTES.get(self.encoding)
        if pixel_bytes is None:
            raise ValueError(f"unknown image encoding {self.encoding!r}")
        if len(self.data) != self.width * self.height * pixel_bytes:
            raise ValueError(
                f"{self.encoding} image data does not match {self.width}x{self.height}"
            )


@dataclass(frozen=True)
class CameraIntrinsics:
    """An undistorted pinhole camera."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_hfov(cls, width: int, height: int, hfov_deg: float) -> CameraIntrinsics:
        """fx = fy = (W/2) / tan(hfov/2), principal point at the image centre."""
        f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(width, height, f, f, width / 2.0, height / 2.0)

    def k(self) -> list[float]:
        return [self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0]

    def p(self) -> list[float]:
        return [self.fx, 0.0, self.cx, 0.0, 0.0, self.fy, self.cy, 0.0, 0.0, 0.0, 1.0, 0.0]


@dataclass(frozen=True)
class PlanarPose:
    """A pose on the ground plane (z is the height of the frame above it)."""

    stamp_ns: int
    x: float
    y: float
    yaw: float
    z: float = 0.0

    def quaternion(self) -> tuple[float, float, float, float]:
        """(x, y, z, w) of a rotation by yaw about +z."""
        return (0.0, 0.0, math.sin(self.yaw / 2.0), math.cos(self.yaw / 2.0))


@dataclass(frozen=True)
class OdometrySample:
    """Integrated wheel odometry: pose in the odom frame, velocities in the base frame."""

    pose: PlanarPose
    linear_velocity: float
    angular_velocity: float


# -- atomic output --------------------------------------------------------------------------------


class _AtomicTarget:
    """A temporary folder beside `final`; `commit` renames the finished output into place.

    The output keeps its final name inside the temporary folder because rosbag2 names its
    database after the bag directory, and the rename must not change the contents.
    """

    def __init__(self, final: Path) -> None:
        self.final = final
        final.parent.mkdir(parents=True, exist_ok=True)
        self._tmpdir = Path(
            tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".tmp", dir=final.parent)
        )
        self.path = self._tmpdir / final.name

    def commit(self) -> None:
        if self.final.is_dir() and not self.final.is_symlink():
            # os.replace cannot replace a non-empty directory: move the old one aside first.
            os.replace(self.final, self._tmpdir / ".old")
        os.replace(self.path, self.final)
        shutil.rmtree(self._tmpdir, ignore_errors=True)

    def discard(self) -> None:
        shutil.rmtree(self._tmpdir, ignore_errors=True)


def output_path(out_dir: Path, stem: str, fmt: Format) -> Path:
    """Where `open_writer` puts format `fmt` of the log `stem` (a directory for db3)."""
    names = {
        "ros2mcap": f"{stem}.ros2.mcap",
        "foxglove": f"{stem}.foxglove.mcap",
        "bag": f"{stem}.bag",
        "db3": f"{stem}.rosbag2",
    }
    return out_dir / names[fmt]


# -- the writer interface -------------------------------------------------------------------------


class CameraLogWriter(ABC):
    """Writes one log; use as a context manager (an exception discards the partial output).

    Channels are registered on their first message, so a log holds only the topics written.
    Messages should be written in log-time order. `log_time_ns` defaults to the stamp.
    """

    def __init__(self, path: Path, topics: Topics | None = None) -> None:
        self.final_path = path
        self.topics = topics or Topics()
        self._target = _AtomicTarget(path)
        self._closed = False

    @abstractmethod
    def write_image(self, frame: ImageFrame, log_time_ns: int | None = None) -> None: ...

    @abstractmethod
    def write_camera_info(
        self,
        camera: CameraIntrinsics,
        stamp_ns: int,
        log_time_ns: int | None = None,
        topic: str | None = None,
    ) -> None:
        """CameraInfo on `topic` (default `Topics.camera_info`)."""

    @abstractmethod
    def write_odometry(self, odom: OdometrySample, log_time_ns: int | None = None) -> None: ...

    @abstractmethod
    def write_ground_truth(self, pose: PlanarPose, log_time_ns: int | None = None) -> None: ...

    def add_metadata(self, name: str, data: dict[str, str]) -> None:  # noqa: B027
        """Free-form key-value metadata; containers without a place for it ignore it."""

    @abstractmethod
    def _finish(self) -> None:
        """Complete the file(s) under `self._target.path`."""

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._finish()
            self._target.commit()

    def abort(self) -> None:
        if not self._closed:
            self._closed = True
            try:
                self._finish()
            finally:
                self._target.discard()

    def __enter__(self) -> CameraLogWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def _image_topic(topics: Topics, frame: ImageFrame) -> str:
    if frame.depth:
        return topics.depth_image
    return topics.compressed_image if frame.compressed else topics.raw_image


# -- ROS messages (both ROS versions) ----------------------------------------------------------


class _RosMessages:
    """Builds rosbags message objects for one type store (ROS 1 or ROS 2 field names)."""

    def __init__(self, store: Typestore, ros1: bool) -> None:
        self.store = store
        self.ros1 = ros1
        self.types: Any = store.types
        self._seq: dict[str, int] = {}

    def _time(self, stamp_ns: int) -> Any:
        sec, nsec = divmod(stamp_ns, 1_000_000_000)
        return self.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)

    def _header(self, topic: str, stamp_ns: int, frame_id: str) -> Any:
        header_type = self.types["std_msgs/msg/Header"]
        if not self.ros1:
            return header_type(stamp=self._time(stamp_ns), frame_id=frame_id)
        seq = self._seq.get(topic, 0)
        self._seq[topic] = seq + 1
        return header_type(seq=seq, stamp=self._time(stamp_ns), frame_id=frame_id)

    def image(self, topic: str, frame: ImageFrame, frame_id: str) -> tuple[str, Any]:
        header = self._header(topic, frame.stamp_ns, frame_id)
        data = np.frombuffer(frame.data, dtype=np.uint8)
        if frame.compressed:
            typename = "sensor_msgs/msg/CompressedImage"
            return typename, self.types[typename](header=header, format=frame.encoding, data=data)
        typename = "sensor_msgs/msg/Image"
        step = frame.width * _PIXEL_BYTES[frame.encoding]
        msg = self.types[typename](
            header=header,
            height=frame.height,
            width=frame.width,
            encoding=frame.encoding,
            is_bigendian=0,
            step=step,
            data=data,
        )
        return typename, msg

    def camera_info(
        self, topic: str, camera: CameraIntrinsics, stamp_ns: int, frame_id: str
    ) -> tuple[str, Any]:
        typename = "sensor_msgs/msg/CameraInfo"
        roi = self.types["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        arrays = {
            "d": np.zeros(5, dtype=np.float64),
            "k": np.array(camera.k(), dtype=np.float64),
            "r": np.eye(3, dtype=np.float64).ravel(),
            "p": np.array(camera.p(), dtype=np.float64),
        }
        if self.ros1:  # ROS 1 spells the matrices in capitals
            arrays = {name.upper(): value for name, value in arrays.items()}
        msg = self.types[typename](
            header=self._header(topic, stamp_ns, frame_id),
            height=camera.height,
            width=camera.width,
            distortion_model="plumb_bob",
            binning_x=0,
            binning_y=0,
            roi=roi,
            **arrays,
        )
        return typename, msg

    def _pose(self, pose: PlanarPose) -> Any:
        qx, qy, qz, qw = pose.quaternion()
        return self.types["geometry_msgs/msg/Pose"](
            position=self.types["geometry_msgs/msg/Point"](x=pose.x, y=pose.y, z=pose.z),
            orientation=self.types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        )

    def _vector(self, x: float, y: float, z: float) -> Any:
        return self.types["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)

    def odometry(self, topic: str, odom: OdometrySample, topics: Topics) -> tuple[str, Any]:
        typename = "nav_msgs/msg/Odometry"
        twist = self.types["geometry_msgs/msg/Twist"](
            linear=self._vector(odom.linear_velocity, 0.0, 0.0),
            angular=self._vector(0.0, 0.0, odom.angular_velocity),
        )
        msg = self.types[typename](
            header=self._header(topic, odom.pose.stamp_ns, topics.odom_frame),
            child_frame_id=topics.base_frame,
            pose=self.types["geometry_msgs/msg/PoseWithCovariance"](
                pose=self._pose(odom.pose), covariance=_diagonal(_ODOM_POSE_COV)
            ),
            twist=self.types["geometry_msgs/msg/TwistWithCovariance"](
                twist=twist, covariance=_diagonal(_ODOM_TWIST_COV)
            ),
        )
        return typename, msg

    def pose_stamped(self, topic: str, pose: PlanarPose, frame_id: str) -> tuple[str, Any]:
        typename = "geometry_msgs/msg/PoseStamped"
        header = self._header(topic, pose.stamp_ns, frame_id)
        return typename, self.types[typename](header=header, pose=self._pose(pose))


def _diagonal(values: Iterable[float]) -> np.ndarray[Any, np.dtype[np.float64]]:
    return np.diag(np.asarray(list(values), dtype=np.float64)).ravel()


class _RosWriter(CameraLogWriter):
    """Shared message building for the three ROS containers; subclasses only `_emit`."""

    def __init__(self, path: Path, topics: Topics | None, store: Typestore, ros1: bool) -> None:
        super().__init__(path, topics)
        self._msgs = _RosMessages(store, ros1)

    @abstractmethod
    def _emit(
        self, topic: str, typename: str, message: Any, stamp_ns: int, log_ns: int
    ) -> None: ...

    def write_image(self, frame: ImageFrame, log_time_ns: int | None = None) -> None:
        topic = _image_topic(self.topics, frame)
        typename, msg = self._msgs.image(topic, frame, self.topics.camera_frame)
        self._emit(topic, typename, msg, frame.stamp_ns, _or(log_time_ns, frame.stamp_ns))

    def write_camera_info(
        self,
        camera: CameraIntrinsics,
        stamp_ns: int,
        log_time_ns: int | None = None,
        topic: str | None = None,
    ) -> None:
        topic = topic or self.topics.camera_info
        typename, msg = self._msgs.camera_info(topic, camera, stamp_ns, self.topics.camera_frame)
        self._emit(topic, typename, msg, stamp_ns, _or(log_time_ns, stamp_ns))

    def write_odometry(self, odom: OdometrySample, log_time_ns: int | None = None) -> None:
        topic = self.topics.odometry
        typename, msg = self._msgs.odometry(topic, odom, self.topics)
        stamp = odom.pose.stamp_ns
        self._emit(topic, typename, msg, stamp, _or(log_time_ns, stamp))

    def write_ground_truth(self, pose: PlanarPose, log_time_ns: int | None = None) -> None:
        topic = self.topics.ground_truth
        typename, msg = self._msgs.pose_stamped(topic, pose, self.topics.map_frame)
        self._emit(topic, typename, msg, pose.stamp_ns, _or(log_time_ns, pose.stamp_ns))


def _or(value: int | None, default: int) -> int:
    return default if value is None else value


# -- the MCAP containers ----------------------------------------------------------------------


class _McapBase:
    """An mcap.writer.Writer on an open file, with per-channel sequence numbers."""

    def __init__(self, path: Path, profile: str, compression: McapCompression) -> None:
        self._file = path.open("wb")
        self.mcap = McapWriter(self._file, compression=_MCAP_COMPRESSION[compression])
        self.mcap.start(profile=profile, library=MCAP_LIBRARY)
        self.channels: dict[str, int] = {}
        self._sequence: dict[int, int] = {}

    def add(self, channel: int, data: bytes, stamp_ns: int, log_ns: int) -> None:
        seq = self._sequence.get(channel, 0)
        self._sequence[channel] = seq + 1
        self.mcap.add_message(
            channel_id=channel, log_time=log_ns, publish_time=stamp_ns, sequence=seq, data=data
        )

    def finish(self) -> None:
        try:
            self.mcap.finish()  # type: ignore[no-untyped-call, unused-ignore]
        finally:
            self._file.close()


class Ros2McapWriter(_RosWriter):
    """MCAP, profile ros2: CDR messages with ros2msg schemas."""

    def __init__(
        self, path: Path, topics: Topics | None = None, compression: McapCompression = "zstd"
    ) -> None:
        super().__init__(path, topics, get_typestore(Stores.ROS2_HUMBLE), ros1=False)
        self._out = _McapBase(self._target.path, "ros2", compression)
        self._schemas: dict[str, int] = {}

    def _channel(self, topic: str, typename: str) -> int:
        channel = self._out.channels.get(topic)
        if channel is None:
            schema = self._schemas.get(typename)
            if schema is None:
                msgdef, _ = self._msgs.store.generate_msgdef(typename, ros_version=2)
                schema = self._out.mcap.register_schema(typename, "ros2msg", msgdef.encode())
                self._schemas[typename] = schema
            channel = self._out.mcap.register_channel(topic, "cdr", schema)
            self._out.channels[topic] = channel
        return channel

    def _emit(self, topic: str, typename: str, message: Any, stamp_ns: int, log_ns: int) -> None:
        data = bytes(self._msgs.store.serialize_cdr(message, typename))
        self._out.add(self._channel(topic, typename), data, stamp_ns, log_ns)

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._out.mcap.add_metadata(name, data)

    def _finish(self) -> None:
        self._out.finish()


class FoxgloveMcapWriter(CameraLogWriter):
    """MCAP with Foxglove protobuf schemas."""

    def __init__(
        self, path: Path, topics: Topics | None = None, compression: McapCompression = "zstd"
    ) -> None:
        super().__init__(path, topics)
        self._out = _McapBase(self._target.path, "", compression)

    def _emit(self, topic: str, message: Message, stamp_ns: int, log_ns: int) -> None:
        channel = self._out.channels.get(topic)
        if channel is None:
            schema = register_schema(self._out.mcap, type(message))
            channel = self._out.mcap.register_channel(topic, "protobuf", schema)
            self._out.channels[topic] = channel
        self._out.add(channel, message.SerializeToString(), stamp_ns, log_ns)

    def write_image(self, frame: ImageFrame, log_time_ns: int | None = None) -> None:
        msg: Message
        frame_id = self.topics.camera_frame
        if frame.compressed:
            msg = FoxCompressedImage(
                timestamp=_timestamp(frame.stamp_ns),
                frame_id=frame_id,
                data=frame.data,
                format=frame.encoding,
            )
        else:
            msg = FoxRawImage(
                timestamp=_timestamp(frame.stamp_ns),
                frame_id=frame_id,
                width=frame.width,
                height=frame.height,
                encoding=frame.encoding,
                step=frame.width * _PIXEL_BYTES[frame.encoding],
                data=frame.data,
            )
        topic = _image_topic(self.topics, frame)
        self._emit(topic, msg, frame.stamp_ns, _or(log_time_ns, frame.stamp_ns))

    def write_camera_info(
        self,
        camera: CameraIntrinsics,
        stamp_ns: int,
        log_time_ns: int | None = None,
        topic: str | None = None,
    ) -> None:
        msg = CameraCalibration(
            timestamp=_timestamp(stamp_ns),
            frame_id=self.topics.camera_frame,
            width=camera.width,
            height=camera.height,
            distortion_model="plumb_bob",
            D=[0.0] * 5,
            K=camera.k(),
            R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            P=camera.p(),
        )
        topic = topic or self.topics.camera_info
        self._emit(topic, msg, stamp_ns, _or(log_time_ns, stamp_ns))

    def _pose_in_frame(self, pose: PlanarPose, frame_id: str) -> PoseInFrame:
        qx, qy, qz, qw = pose.quaternion()
        msg = PoseInFrame(timestamp=_timestamp(pose.stamp_ns), frame_id=frame_id, pose=FoxPose())
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = pose.x, pose.y, pose.z
        q = msg.pose.orientation
        q.x, q.y, q.z, q.w = qx, qy, qz, qw
        return msg

    def write_odometry(self, odom: OdometrySample, log_time_ns: int | None = None) -> None:
        # PoseInFrame has no twist: the velocities are dropped in this container.
        msg = self._pose_in_frame(odom.pose, self.topics.odom_frame)
        stamp = odom.pose.stamp_ns
        self._emit(self.topics.odometry, msg, stamp, _or(log_time_ns, stamp))

    def write_ground_truth(self, pose: PlanarPose, log_time_ns: int | None = None) -> None:
        msg = self._pose_in_frame(pose, self.topics.map_frame)
        self._emit(self.topics.ground_truth, msg, pose.stamp_ns, _or(log_time_ns, pose.stamp_ns))

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._out.mcap.add_metadata(name, data)

    def _finish(self) -> None:
        self._out.finish()


def _timestamp(stamp_ns: int) -> Timestamp:
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    return Timestamp(seconds=sec, nanos=nsec)


# -- the rosbag containers ----------------------------------------------------------------------


class Ros1BagWriter(_RosWriter):
    """ROS 1 bag v2.0 through rosbags.rosbag1."""

    def __init__(
        self, path: Path, topics: Topics | None = None, compression: BagCompression = "none"
    ) -> None:
        super().__init__(path, topics, get_typestore(Stores.ROS1_NOETIC), ros1=True)
        self._bag = Bag1Writer(self._target.path)
        if compression != "none":
            self._bag.set_compression(_BAG_COMPRESSION[compression])
        self._bag.open()
        self._connections: dict[str, Any] = {}

    def _emit(self, topic: str, typename: str, message: Any, stamp_ns: int, log_ns: int) -> None:
        conn = self._connections.get(topic)
        if conn is None:
            conn = self._bag.add_connection(topic, typename, typestore=self._msgs.store)
            self._connections[topic] = conn
        self._bag.write(conn, log_ns, self._msgs.store.serialize_ros1(message, typename))

    def _finish(self) -> None:
        self._bag.close()


class Rosbag2Writer(_RosWriter):
    """ROS 2 bag directory with sqlite3 storage, through rosbags.rosbag2 (bag version 9)."""

    def __init__(self, path: Path, topics: Topics | None = None) -> None:
        super().__init__(path, topics, get_typestore(Stores.ROS2_HUMBLE), ros1=False)
        self._bag = Bag2Writer(self._target.path, version=9, storage_plugin=StoragePlugin.SQLITE3)
        self._bag.open()
        self._connections: dict[str, Any] = {}

    def _emit(self, topic: str, typename: str, message: Any, stamp_ns: int, log_ns: int) -> None:
        conn = self._connections.get(topic)
        if conn is None:
            conn = self._bag.add_connection(topic, typename, typestore=self._msgs.store)
            self._connections[topic] = conn
        self._bag.write(conn, log_ns, self._msgs.store.serialize_cdr(message, typename))

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        # rosbag2 has one flat custom_data map in metadata.yaml.
        for key, value in data.items():
            self._bag.set_custom_data(f"{name}.{key}", value)

    def _finish(self) -> None:
        self._bag.close()


def open_writer(
    fmt: Format,
    path: Path,
    topics: Topics | None = None,
    *,
    mcap_compression: McapCompression = "zstd",
    bag_compression: BagCompression = "none",
) -> CameraLogWriter:
    """A writer of format `fmt` that will create `path` (replacing it) when closed."""
    if fmt == "ros2mcap":
        return Ros2McapWriter(path, topics, mcap_compression)
    if fmt == "foxglove":
        return FoxgloveMcapWriter(path, topics, mcap_compression)
    if fmt == "bag":
        return Ros1BagWriter(path, topics, bag_compression)
    if fmt == "db3":
        return Rosbag2Writer(path, topics)
    raise ValueError(f"unknown format {fmt!r}; choose from {', '.join(FORMATS)}")


def parse_formats(text: str) -> list[Format]:
    """'ros2mcap,bag' -> ["ros2mcap", "bag"] (order kept, duplicates dropped)."""
    chosen: list[Format] = []
    for name in (part.strip() for part in text.split(",")):
        if name not in FORMATS:
            raise ValueError(f"unknown format {name!r}; choose from {', '.join(FORMATS)}")
        if name not in chosen:
            chosen.append(name)
    if not chosen:
        raise ValueError("no output format given")
    return chosen


def path_size(path: Path) -> int:
    """Bytes in a file, or in all files under a directory (a rosbag2 bag)."""
    if path.is_dir():
        return sum(p.stat().st_size for p in sorted(path.rglob("*")) if p.is_file())
    return path.stat().st_size
