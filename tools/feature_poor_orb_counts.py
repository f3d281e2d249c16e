#!/usr/bin/env python3
"""Median ORB features a frame by the frame's size, as it is and enlarged (issue #22 item 2):
the tuning sets' frames (RTAB-Map, drive_loops, drive_parked; every third one) area-shrunk to
a longer side of N px, their aspect kept, then given to verification's ORB (1000 features at
most) as they are and enlarged (bicubic) to 320 px. A table of docs/results.md ("Why 160 px
and 320 px").

    python tools/feature_poor_orb_counts.py
"""

from __future__ import annotations

import sys
from statistics import median

import cv2
import numpy as np

import feature_poor_table as fpt
from loggen import shrink_log

SIDES = (64, 96, 128, 160, 192, 256)
WORKING_SIZE = 320


def enlarged(gray: shrink_log.Gray, side: int) -> shrink_log.Gray:
    scale = side / max(gray.shape)
    size = (round(gray.shape[1] * scale), round(gray.shape[0] * scale))
    return np.asarray(cv2.resize(gray, size, interpolation=cv2.INTER_CUBIC), dtype=np.uint8)


def main() -> int:
    orb = cv2.ORB_create(nfeatures=1000)
    every = fpt.sources(fpt.DATA)
    print("| data | " + " | ".join(str(side) for side in SIDES) + " |")
    print("|---" * (len(SIDES) + 1) + "|")
    for source in every["rtabmap"] + every["samples"][:2]:
        frames = [gray for _, gray in source.frames()][::3]
        cells = []
        for side in SIDES:
            as_is, bigger = [], []
            for gray in frames:
                height, width = gray.shape
                small = shrink_log.shrink_gray(gray, side, round(height * side / width))
                as_is.append(len(orb.detect(small, None)))
                bigger.append(len(orb.detect(enlarged(small, WORKING_SIZE), None)))
            cells.append(f"{median(as_is):g} / {median(bigger):g}")
        print(f"| {source.name}, as is / enlarged | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
