"""Copying a ROS 1 bag or a rosbag2 bag message by message, with the raw bytes as stored
(`copy_ros1_bag`, `copy_rosbag2`), through rosbags' readers."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Collection, Iterator
from pathlib import Path
from typing import Any, Protocol, TypeVar

import zstandard
from mcap.writer import Writer
from rosbags.interfaces import Connection, ConnectionExtRosbag1, MessageDefinitionFormat
from rosbags.rosbag1 import Reader as Ros1Reader
from rosbags.rosbag2 import Reader as Ros2Reader
from rosbags.rosbag2.metadata import dump_qos_v8
from rosbags.rosbag2.reader import DirectoryReader
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from .copying import Copied, CopyHooks, guarded_reads, reading_errors


class _Storage(Protocol):
    """The part of a rosbags storage reader (sqlite3, MCAP) used here."""

    connections: list[Connection]

    def messages(
        self,
        connections: Collection[Connection],
        start: int | None = None,
        stop: int | None = None,
    ) -> Iterator[tuple[Connection, int, bytes]]: ...


class _Openable(Protocol):
    def open(self) -> None: ...

    def close(self) -> None: ...


R = TypeVar("R", bound=_Openable)


@contextlib.contextmanager
def open_bag(path: Path, factory: Callable[[Path], R]) -> Iterator[R]:
    """An open rosbags reader; only opening it counts as reading (SourceError)."""
    with reading_errors(path):
        reader = factory(path)
        reader.open()
    try:
        yield reader
    finally:
        with contextlib.suppress(Exception):
            reader.close()


def _ros1_schema_name(msgtype: str) -> str:
    """rosbags spells every type the ROS 2 way; ROS 1 has no `/msg/` part."""
    package, _, name = msgtype.rpartition("/")
    return f"{package.removesuffix('/msg')}/{name}"


def _ros1_channel_metadata(connection: Connection) -> dict[str, str]:
    metadata = {"md5sum": connection.digest}
    ext = connection.ext
    if isinstance(ext, ConnectionExtRosbag1):
        if ext.callerid is not None:
            metadata["callerid"] = ext.callerid
        if ext.latching is not None:
            metadata["latching"] = "true" if ext.latching else "false"  # the ros1 profile's form
    return metadata


class _BagCopier:
    """Copies the messages of a ROS 1 or rosbag2 bag (via rosbags) with their raw bytes."""

    def __init__(self, writer: Writer, hooks: CopyHooks) -> None:
        self.writer = writer
        self.hooks = hooks
        self.schema_ids: dict[tuple[str, str, bytes], int] = {}
        self.channel_ids: dict[Any, int] = {}
        self.topics: dict[Any, str] = {}  # channel key -> topic, of the copied channels
        self.dropped: set[str] = set()
        self.copied = 0

    def schema(self, name: str, encoding: str, data: bytes) -> int:
        key = (name, encoding, data)
        if key not in self.schema_ids:
            self.schema_ids[key] = self.writer.register_schema(name, encoding, data)
        return self.schema_ids[key]

    def channel(
        self, key: Any, topic: str, encoding: str, schema_id: int, metadata: dict[str, str]
    ) -> None:
        if not self.hooks.keeps_topic(topic):
            self.dropped.add(topic)
        elif key not in self.channel_ids:
            self.channel_ids[key] = self.writer.register_channel(
                topic, encoding, schema_id, metadata
            )
            self.topics[key] = topic
            self.hooks.channel_copied(topic, encoding, schema_id, metadata)

    def message(self, key: Any, timestamp: int, data: bytes) -> None:
        channel_id = self.channel_ids.get(key)
        if channel_id is None:
            return  # one of our previous channels
        self.hooks.before_message(timestamp)
        written = bytes(data)
        # Bags record one time per message: it is both the log and the publish time.
        self.writer.add_message(channel_id, timestamp, written, timestamp, 0)
        self.hooks.message_copied(self.topics[key], timestamp, written)
        self.copied += 1

    def copy_ros1(self, path: Path) -> None:
        """Raises SourceError when the bag cannot be read."""
        with open_bag(path, Ros1Reader) as reader:
            for conn in sorted(reader.connections, key=lambda c: c.id):
                data = conn.msgdef.data.encode()
                schema_id = self.schema(_ros1_schema_name(conn.msgtype), "ros1msg", data)
                self.channel(conn.id, conn.topic, "ros1", schema_id, _ros1_channel_metadata(conn))
            for conn, timestamp, raw in guarded_reads(path, reader.messages()):
                self.message(conn.id, timestamp, raw)

    def copy_rosbag2(self, path: Path) -> None:
        """Raises SourceError when the bag cannot be read."""
        with open_bag(path, Ros2Reader) as reader:
            definitions = _Ros2Definitions(reader)
            storages = _storages(reader)
            keys: dict[tuple[int, int], tuple[str, ...]] = {}
            for number, storage in enumerate(storages):
                for conn in storage.connections:
                    keys[number, conn.id] = self._rosbag2_channel(conn, definitions)
            decompress = _message_decompressor(reader.compression_mode)
            for number, storage in enumerate(storages):
                messages = storage.messages(storage.connections)
                for conn, timestamp, raw in guarded_reads(path, messages):
                    self.message(keys[number, conn.id], timestamp, decompress(raw))

    def _rosbag2_channel(self, conn: Connection, definitions: _Ros2Definitions) -> tuple[str, ...]:
        """Registers the connection's channel and returns its key: the same for the same
        channel in every storage file of a split bag."""
        encoding, data = definitions.get(conn)
        schema_id = self.schema(conn.msgtype, encoding, data)
        qos_profiles = list(getattr(conn.ext, "offered_qos_profiles", []))
        qos = dump_qos_v8(qos_profiles) if qos_profiles else ""
        message_encoding = getattr(conn.ext, "serialization_format", "cdr")
        metadata = {"offered_qos_profiles": qos} if qos else {}
        key = (conn.topic, conn.msgtype, message_encoding, qos)
        self.channel(key, conn.topic, message_encoding, schema_id, metadata)
        return key


def _storages(reader: Ros2Reader) -> list[_Storage]:
    # The storage files are read one by one: rosbags 0.11's folder reader yields no message
    # at all for a topic whose QoS in metadata.yaml differs from the one in the storage file.
    storage = reader.storage
    if isinstance(storage, DirectoryReader):
        return list(storage.storages)
    return [storage]


def _message_decompressor(mode: str | None) -> Callable[[bytes], bytes]:
    if mode != "message":
        return lambda raw: raw
    decompressor = zstandard.ZstdDecompressor()
    # Frames may not record their size; a stream reader does not need it.
    return lambda raw: decompressor.decompressobj().decompress(raw)


class _Ros2Definitions:
    """Message definitions of a rosbag2 bag, generated from rosbags' types when missing."""

    def __init__(self, reader: Ros2Reader) -> None:
        self.by_type = {
            c.msgtype: c.msgdef
            for c in reader.connections
            if c.msgdef.format != MessageDefinitionFormat.NONE
        }
        self.distro = reader.ros_distro
        self._typestore: Typestore | None = None

    def get(self, conn: Connection) -> tuple[str, bytes]:
        """(schema encoding, data); encoding "" and no data when no definition is known."""
        msgdef = conn.msgdef
        if msgdef.format == MessageDefinitionFormat.NONE:
            msgdef = self.by_type.get(conn.msgtype, msgdef)
        if msgdef.format == MessageDefinitionFormat.MSG:
            return "ros2msg", msgdef.data.encode()
        if msgdef.format == MessageDefinitionFormat.IDL:
            return "ros2idl", msgdef.data.encode()
        return self._generate(conn.msgtype)

    def _generate(self, msgtype: str) -> tuple[str, bytes]:
        typestore = self._store()
        if msgtype not in typestore.fielddefs:
            return "", b""  # unknown type: the channel keeps its type name, without definition
        text, _ = typestore.generate_msgdef(msgtype, ros_version=2)
        return "ros2msg", text.encode()

    def _store(self) -> Typestore:
        if self._typestore is None:
            try:
                store = Stores(f"ros2_{self.distro}")
            except ValueError:
                store = Stores.LATEST
            self._typestore = get_typestore(store)
        return self._typestore


def copy_ros1_bag(path: Path, writer: Writer, hooks: CopyHooks) -> Copied:
    """Every message of the ROS 1 bag at `path` into `writer`, but the ones `hooks` leaves
    out. Raises SourceError when the bag cannot be read."""
    bag = _BagCopier(writer, hooks)
    bag.copy_ros1(path)
    return Copied(bag.copied, sorted(bag.dropped))


def copy_rosbag2(path: Path, writer: Writer, hooks: CopyHooks) -> Copied:
    """As `copy_ros1_bag`, for a rosbag2 bag (its folder, or a bare .db3 file)."""
    bag = _BagCopier(writer, hooks)
    bag.copy_rosbag2(path)
    return Copied(bag.copied, sorted(bag.dropped))
