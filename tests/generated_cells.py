"""Small cells of the generalization matrix (tools/reproduce/generalization_matrix.py), for
tests that need a real drive with its truth: the frames, the camera and the generator's poses.
The `one_hz` and `two_hz` fixtures (conftest.py) generate them once per test run."""

from __future__ import annotations

import csv
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from doseqslam_logs.sources import opened
from doseqslam_logs.sources.camera_info import find_camera_info
from doseqslam_logs.sources.images import decode_gray
from doseqslam_logs.verification.geometry import Intrinsics
from doseqslam_logs.verification.metric_pose import OPTICAL_TO_BODY
from doseqslam_logs.verification.motion import CameraPath
from loggen import make_sample_logs as gen
from reproduce import generalization_matrix as matrix

CAMERA = "/camera/image/compressed"
ONE_HZ = replace(matrix.BASE, name="1Hz", rate=1.0, seed=1)
TWO_HZ = replace(matrix.BASE, name="2Hz", rate=2.0, seed=1)


def generate(config: gen.Config, out: Path) -> Path:
    """The cell's log, ground truth and poses written into `out` (named after the cell)."""
    gen.generate(config, out, jobs=1, progress=False)
    return out


def true_path(cell: Path, name: str = "1Hz") -> CameraPath:
    """The generator's poses as the camera path (an odometry without drift)."""
    with open(cell / f"{name}.poses.csv") as file:
        rows = [(float(r["x"]), float(r["y"]), float(r["yaw"])) for r in csv.DictReader(file)]
    poses = np.asarray(rows)
    positions = np.column_stack([poses[:, :2], np.zeros(len(poses))])
    body = Rotation.from_euler("z", poses[:, 2:3])
    orientations = (body * Rotation.from_matrix(OPTICAL_TO_BODY)).as_quat()
    return CameraPath("/truth", positions, np.ones(len(poses), bool), orientations)


def frames_and_camera(cell: Path, name: str = "1Hz") -> tuple[list[np.ndarray], Intrinsics]:
    """Every frame of the cell's log, grey, and its camera's intrinsics."""
    log = cell / f"{name}.ros2.mcap"
    with opened(log) as source:
        frames = [decode_gray(m) for m in source.image_messages(CAMERA)]
    info = find_camera_info(log, CAMERA).info
    assert info is not None
    return frames, Intrinsics(info.fx, info.fy, info.cx, info.cy)
