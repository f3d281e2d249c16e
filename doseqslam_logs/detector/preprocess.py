"""Per-frame preprocessing (paper III-A): downsample and patch-normalize a gray image."""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float32]

# A patch whose population std is below this is flat (e.g. saturated sky) and becomes zeros.
FLAT_PATCH_STD = 1e-6


def downsample(gray: npt.NDArray[np.uint8], width: int, height: int) -> FloatArray:
    """Resize to width x height with area averaging (antialiased, like MATLAB `imresize`).

    Raises ValueError for an image that is not 2-D or is empty.
    """
    if gray.ndim != 2 or gray.size == 0:
        raise ValueError(f"expected a non-empty 2-D gray image, got shape {gray.shape}")
    small = cv2.resize(gray.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)
    return np.asarray(small, dtype=np.float32)


def patch_normalize(image: FloatArray, patch: int) -> FloatArray:
    """Z-score every non-overlapping patch x patch block (population std; flat patch -> 0)."""
    h, w = image.shape
    blocks = image.astype(np.float64).reshape(h // patch, patch, w // patch, patch)
    mean = blocks.mean(axis=(1, 3), keepdims=True)
    std = blocks.std(axis=(1, 3), keepdims=True)
    safe = np.where(std < FLAT_PATCH_STD, 1.0, std)
    normalized = np.where(std < FLAT_PATCH_STD, 0.0, (blocks - mean) / safe)
    return normalized.reshape(h, w).astype(np.float32)


def frame_vector(gray: npt.NDArray[np.uint8], width: int, height: int, patch: int) -> FloatArray:
    """The chi = width * height vector that the difference rows compare (paper eq. 1)."""
    return patch_normalize(downsample(gray, width, height), patch).reshape(-1)
