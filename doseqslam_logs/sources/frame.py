"""The unit that flows from sources to the detector: one decoded camera frame."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt


@dataclass(frozen=True)
class Frame:
    """A decoded gray frame and its times.

    `timestamp_ns` is the time the detector uses (header stamp or log time, as asked); the
    others are kept so outputs can name the frame both ways.
    """

    index: int  # position among the frames given to the detector (0-based)
    timestamp_ns: int
    log_time_ns: int
    header_stamp_ns: int | None
    image: npt.NDArray[np.uint8]
