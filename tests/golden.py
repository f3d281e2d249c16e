"""Measured figures that several tests check, in one place (docs/results.md has them with the
commands). A change of the detector that moves one of them on purpose changes it here once."""

from __future__ import annotations

# sample_logs/drive_loops.ros2.mcap (240 frames), the paper's parameters, no verification:
# every reported pair is true against drive_loops.gt.npz (exact cell).
DRIVE_LOOPS_FRAMES = 240
DRIVE_LOOPS_PAPER_PAIRS = 47
DRIVE_LOOPS_GT_LOOP_EVENTS = 123

# ../shared/data/rtabmap_samples_loop: 84 images, samples_GT.bmp.
RTABMAP_FRAMES = 84
RTABMAP_LOOP_EVENTS = 44
RTABMAP_PAPER_TP = 9  # DOSeqSLAM, kappa 10 s, --no-verify: R@P100 9 / 44
RTABMAP_VERIFIED_MIN_TP = 38  # the defaults with verification: 38 TP / 0 FP (86.4 %)
