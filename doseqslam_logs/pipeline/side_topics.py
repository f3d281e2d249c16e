"""The other topics a run reads (its pose topic, the camera's CameraInfo), collected in the
replay's pass over the camera topic: each chunk of the log is read once for them all, and the
pose topic once in the whole run.

Depth images are not collected here: only the accepted pairs' frames need one, and they are
known after the verification; keeping every depth image until then would hold the log's depth
stream in memory. The metric stage reads those few through the index.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass

from ..errors import SourceError
from ..sources.base import ImageMessage, SideMessage, Source
from ..sources.camera_info import CameraInfoReader, CameraInfoSearch
from ..sources.poses import PoseReader, PoseTrack, run_pose_topic


@dataclass
class SideTopics:
    """What the replay's pass collects besides the frames (None: not collected, read later)."""

    poses: PoseReader | None = None
    camera_info: CameraInfoReader | None = None

    @classmethod
    def for_run(
        cls, source: Source, image_topic: str, pose_topic: str | None, camera_info: bool
    ) -> SideTopics:
        """The readers for a run: `pose_topic` (None: the log's default one, "": none) and,
        when `camera_info`, the CameraInfo of `image_topic`'s camera.

        Raises SourceError for an asked pose topic that is missing or not a pose type (as
        reading it later would, before the replay spends its time).
        """
        topic = run_pose_topic(source, pose_topic)
        poses = PoseReader(source, topic) if topic else None
        info = CameraInfoReader(source, image_topic) if camera_info else None
        return cls(poses, info if info is not None and info.search.topic else None)

    @property
    def topics(self) -> list[str]:
        """The topics to read in the replay's pass."""
        topics = [] if self.poses is None else [self.poses.topic]
        return topics + ([] if self.camera_info is None else [self.camera_info.search.topic])

    def split(self, messages: Iterable[ImageMessage | SideMessage]) -> Iterator[ImageMessage]:
        """The image messages; the others are handed to their readers on the way."""
        poses, camera_info = self.poses, self.camera_info
        pose_topic = poses.topic if poses is not None else None
        for message in messages:
            if isinstance(message, ImageMessage):
                yield message
            elif message.topic == pose_topic and poses is not None:
                poses.add_side(message)
            elif camera_info is not None and message.topic == camera_info.search.topic:
                camera_info.add_side(message)

    def pose_track(self) -> PoseTrack | None:
        """The pose topic's track, None when there is none or it could not be read."""
        if self.poses is None:
            return None
        try:
            return self.poses.track()
        except SourceError:
            return None

    def camera_info_search(self) -> CameraInfoSearch | None:
        """The CameraInfo search (None: not collected). Raises SourceError when the topic
        could not be decoded, as reading it would."""
        return None if self.camera_info is None else self.camera_info.found()
