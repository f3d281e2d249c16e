"""Helpers shared by the detector tests: scripted segmentation and real frames."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt


class ScriptedSegmenter:
    """Starts a sequence exactly at the given frame indices (frame 0 always starts one)."""

    name = "scripted"

    def __init__(self, starts: Iterable[int]) -> None:
        self._starts = set(starts) | {0}
        self._index = -1

    def prepare(self, gray: npt.NDArray[np.uint8]) -> None:
        return None

    def update(self, prepared: None) -> bool:
        self._index += 1
        return self._index in self._starts

    def restart(self, prepared: None) -> None:
        self._index += 1

    def starts_sequence(self, gray: npt.NDArray[np.uint8]) -> bool:
        return self.update(self.prepare(gray))


def noise_frames(count: int, seed: int = 0, shape: tuple[int, int] = (48, 96)) -> list:
    """Distinct random gray frames: no two places look alike."""
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, shape, dtype=np.uint8) for _ in range(count)]


def rtabmap_frames(shared_data: Path) -> list[npt.NDArray[np.uint8]]:
    folder = shared_data / "rtabmap_samples_loop" / "images"
    return [cv2.imread(str(folder / f"{i}.jpg"), cv2.IMREAD_GRAYSCALE) for i in range(1, 85)]


def rtabmap_gt(shared_data: Path) -> npt.NDArray[np.bool_]:
    path = shared_data / "rtabmap_samples_loop" / "samples_GT.bmp"
    return np.asarray(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 0)
