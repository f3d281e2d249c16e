"""The verification's features of every frame, extracted during the replay and kept on disk.

The replay decodes every frame once; without this, verification decodes the frames it checks a
second time (re-reading and decompressing their chunks) and extracts their features again, often
more than once when its bounded cache has let them go (on a long log, about two loads a frame).
So the replay's prepare threads also run `extract_features` on the decoded frame, and the
detector's thread appends the result here in frame order; verification then reads each frame's
features back with one os.pread (the page cache usually answers), identical to what it would
have extracted.

On disk a frame takes 8 + N * (8 + D) bytes (N features of D descriptor bytes: 40 kB at most
with 1000 ORB features), in an unlinked temporary file (TMPDIR) that disappears when the spill
is closed or the process ends. In memory: one 8-byte offset per frame.
"""

from __future__ import annotations

import struct
from array import array
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from ..closing import Closing
from ..detector.params import Parameters
from ..detector.segmentation import OrbFeatures
from ..verification.geometry import FrameFeatures, GrayImage, extract_features
from ..verification.params import VerificationParameters, shares_features
from .frame_spill import FileSpill

# count (uint32), descriptor width (uint32), scale (float64), whether pyramid levels follow
# (uint8), then the keypoints (float32 x, y), the descriptors (uint8) and the levels (uint8).
_HEADER = struct.Struct("<IIdB")


class FeatureSpill(Closing):
    """`extract_features` of each frame, by frame index. Use as a context manager.

    `compute` may run on any thread; `keep` is called in frame order (index 0, 1, ...) from one
    thread (the replay's detector thread); `get` may run on several threads once the replay is
    over.
    """

    def __init__(
        self,
        params: VerificationParameters,
        directory: str | Path | None = None,
        shared: bool = False,
    ) -> None:
        """`shared`: the detector takes these features too (`detector_features`)."""
        self.params = params
        self.shared = shared
        self._spill = FileSpill(directory, what="the frames' features")
        self._offsets = array("q", [0])  # frame i's record: offsets[i] .. offsets[i + 1]

    @property
    def frames(self) -> int:
        return len(self._offsets) - 1

    def compute(self, gray: GrayImage) -> FrameFeatures:
        return extract_features(gray, self.params)

    def detector_features(self, features: FrameFeatures) -> OrbFeatures | None:
        """The features for the detector's segmentation and place index, when shared."""
        if not self.shared or features.levels is None:
            return None
        return OrbFeatures(features.descriptors, features.levels)

    def keep(self, index: int, features: FrameFeatures) -> None:
        """Append frame `index`'s features (the frames must come in order, from 0).

        Raises:
            ValueError: `index` is not the next frame.
            OutputError: the disk refuses the bytes.
        """
        if index != self.frames:
            raise ValueError(f"features of frame {index} kept after {self.frames} frames")
        levels = features.levels
        header = _HEADER.pack(
            features.count, features.descriptors.shape[1], features.scale, levels is not None
        )
        record = header + features.keypoints.tobytes() + features.descriptors.tobytes()
        if levels is not None:
            record += levels.tobytes()
        start = self._offsets[-1]
        self._spill.write(start, memoryview(record))
        self._offsets.append(start + len(record))

    def get(self, index: int) -> FrameFeatures | None:
        """Frame `index`'s features, or None for a frame that was never kept."""
        if not 0 <= index < self.frames:
            return None
        start, end = self._offsets[index], self._offsets[index + 1]
        record = bytearray(end - start)
        self._spill.read_into(start, memoryview(record))
        count, width, scale, has_levels = _HEADER.unpack_from(record)
        keypoints_end = _HEADER.size + 8 * count
        keypoints = np.frombuffer(record, np.float32, 2 * count, _HEADER.size).reshape(count, 2)
        descriptors = np.frombuffer(record, np.uint8, count * width, keypoints_end)
        levels_at = keypoints_end + count * width
        return FrameFeatures(
            keypoints=keypoints,
            descriptors=descriptors.reshape(count, width),
            detector=self.params.feature_detector,
            scale=scale,
            levels=np.frombuffer(record, np.uint8, count, levels_at) if has_levels else None,
        )

    def close(self) -> None:
        self._spill.close()


@contextmanager
def feature_spill_for(
    params: VerificationParameters | None, detector: Parameters
) -> Iterator[FeatureSpill | None]:
    """A FeatureSpill for verification with these parameters, closed (and so gone) when the
    block ends, its features shared with a `detector` of these parameters where they can be
    (`shares_features`); None when verification is off."""
    if params is None:
        yield None
        return
    with FeatureSpill(params, shared=shares_features(detector, params)) as spill:
        yield spill
