#!/usr/bin/env python3
"""Stated covariance against actual error of the recorded metric loop edges (issue #20).

For each annotated log (annotate's defaults; it must carry /ground_truth/pose and /odom): every
reported loop closure with a metric pose is compared with the true relative pose (camera
optical frames, X_match = R X_query + t, as recorded); its NEES (squared error in the stated
covariance's metric: 6 degrees of freedom for a PnP edge, median 5.35 when the covariance is
right; 3 for the rotation block, median 2.37) and its errors are summarised per method, median
/ 95th percentile. `--verbose` prints one line per edge, worst translation error first.

    python -m reproduce.metric_nees ANNOTATED.mcap ... [--verbose]
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.export.loops import frame_times_ns
from doseqslam_logs.sources.poses import read_poses
from doseqslam_logs.verification.metric_pose import OPTICAL_TO_BODY

OPTICAL = Rotation.from_matrix(OPTICAL_TO_BODY)


def camera_poses(path: Path, topic: str, times: Any) -> tuple[Rotation, Any]:
    at = read_poses(path, topic).interpolate(times)
    return Rotation.from_quat(at.quaternions_xyzw) * OPTICAL, np.asarray(at.positions)


def edges(path: Path) -> list[dict[str, Any]]:
    """One dict per metric edge: method, errors, NEES, stated sigmas, inliers."""
    log = read_annotations(path)
    rotations, positions = camera_poses(path, "/ground_truth/pose", frame_times_ns(log))
    rows = []
    for lc in log.reported_loop_closures:
        if not lc.metric_method:
            continue
        q, m = lc.query.index, lc.matched.index
        true_rotation = rotations[m].inv() * rotations[q]
        true_translation = rotations[m].inv().apply(positions[q] - positions[m])
        w = (Rotation.from_quat(lc.metric_rotation_xyzw) * true_rotation.inv()).as_rotvec()
        cov = np.asarray(lc.metric_covariance, np.float64).reshape(6, 6)
        row: dict[str, Any] = {
            "log": path.stem,
            "pair": f"{q}-{m}",
            "method": lc.metric_method,
            "inliers": lc.metric_inliers,
            "r_err_deg": math.degrees(float(np.linalg.norm(w))),
            "nees_r": float(w @ np.linalg.solve(cov[3:, 3:], w)),
            "sigma_r_deg": math.degrees(math.sqrt(np.trace(cov[3:, 3:]) / 3)),
        }
        if lc.metric_method != "rotation_only":
            dt = np.asarray(lc.metric_translation) - true_translation
            error = np.concatenate([dt, w])
            row["t_err_m"] = float(np.linalg.norm(dt))
            row["nees"] = float(error @ np.linalg.solve(cov, error))
            row["nees_t"] = float(dt @ np.linalg.solve(cov[:3, :3], dt))
            row["sigma_t_m"] = math.sqrt(np.trace(cov[:3, :3]) / 3)
        rows.append(row)
    return rows


def summary(rows: list[dict[str, Any]]) -> str:
    lines = []
    for method in sorted({r["method"] for r in rows}):
        mine = [r for r in rows if r["method"] == method]
        cells = []
        for key in ("t_err_m", "r_err_deg", "nees", "nees_t", "nees_r", "sigma_t_m", "sigma_r_deg"):
            values = [r[key] for r in mine if key in r]
            if values:
                cells.append(f"{key} {np.median(values):.3g} / {np.percentile(values, 95):.3g}")
        lines.append(f"{method} ({len(mine)}): " + ", ".join(cells))
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("logs", nargs="+", type=Path)
    parser.add_argument("--verbose", action="store_true", help="one line per edge")
    args = parser.parse_args()
    rows = [row for path in args.logs for row in edges(path)]
    if args.verbose:
        for r in sorted(rows, key=lambda r: -r.get("t_err_m", -1.0)):
            print(
                " ".join(
                    f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in r.items()
                )
            )
    print(summary(rows))


if __name__ == "__main__":
    main()
