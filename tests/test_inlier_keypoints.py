"""The inlier keypoints of each reported loop closure, drawn on both images: on the query image
in `/doseqslam/match/annotations`, on the match image in `/doseqslam/match/image_annotations`,
each point where the pair's accepted check found it, in that image's own pixels."""

from __future__ import annotations

import bisect
import json
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest
from scipy.spatial.transform import Rotation

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.annotations.records import LoopClosureRecord
from doseqslam_logs.detector import Parameters
from doseqslam_logs.pipeline.annotate import AnnotateOptions, annotate_log
from doseqslam_logs.sinks.visualization import (
    ANNOTATIONS_TOPIC,
    INLIER_COLOR,
    MATCH_ANNOTATIONS_TOPIC,
)
from doseqslam_logs.sources import opened
from doseqslam_logs.sources.images import decode_gray
from doseqslam_logs.verification.geometry import MAX_INLIER_POINTS
from loggen import make_sample_logs as gen

SAMPLES = Path(__file__).resolve().parents[1] / "sample_logs"
CAMERA = "/camera/image/compressed"
PROFILES = {
    "ros2": "drive_loops.ros2.mcap",
    "ros1": "drive_loops.bag",
    "json": "drive_loops.foxglove.mcap",
}
POINTS = 1  # foxglove PointsAnnotation type
F64 = npt.NDArray[np.float64]


def drawn_points(annotations: Any) -> list[tuple[int, F64, tuple[float, ...]]]:
    """(type, N x 2 points, outline colour) of each PointsAnnotation of an ImageAnnotations,
    decoded as a ROS message or as a JSON object (plain dicts)."""
    found = []
    for item in annotations.points:
        if isinstance(item, dict):
            xy = [(p["x"], p["y"]) for p in item["points"]]
            color = tuple(item["outline_color"][k] for k in "rgba")
            found.append((item["type"], np.array(xy, np.float64).reshape(-1, 2), color))
        else:
            xy = [(p.x, p.y) for p in item.points]
            color = (item.outline_color.r, item.outline_color.g, item.outline_color.b)
            color += (item.outline_color.a,)
            found.append((item.type, np.array(xy, np.float64).reshape(-1, 2), color))
    return found


def inliers_drawn(annotations: Any) -> F64 | None:
    """The points of the one POINTS annotation (None without), checked to be in our colour."""
    points = [(xy, color) for kind, xy, color in drawn_points(annotations) if kind == POINTS]
    if not points:
        return None
    [(xy, color)] = points
    assert color == pytest.approx(INLIER_COLOR)
    return xy


class Drawn:
    """An annotated log: its camera images, reported loop closures and both annotation topics."""

    def __init__(self, log: Path, output: Path) -> None:
        self.output = output
        with opened(log) as source:
            self.images = {m.log_time_ns: decode_gray(m) for m in source.image_messages(CAMERA)}
        annotated = read_annotations(output)
        self.reported = annotated.reported_loop_closures
        self.intrinsics = annotated.metadata.intrinsics
        with opened(output) as source:
            self.topics = {
                topic: [(m.log_time_ns, m.message) for m in source.messages(topic)]
                for topic in (ANNOTATIONS_TOPIC, MATCH_ANNOTATIONS_TOPIC)
            }

    def at(self, topic: str, log_time_ns: int) -> Any:
        """What a viewer shows of `topic` at this log time: its latest message."""
        messages = self.topics[topic]
        return messages[bisect.bisect_right([t for t, _ in messages], log_time_ns) - 1][1]

    def pairs(self, record: LoopClosureRecord) -> tuple[F64, F64]:
        """The query's and the match's points drawn at this loop closure."""
        query = inliers_drawn(self.at(ANNOTATIONS_TOPIC, record.query.log_time_ns))
        match = inliers_drawn(self.at(MATCH_ANNOTATIONS_TOPIC, record.query.log_time_ns))
        assert query is not None and match is not None
        return query, match


@pytest.fixture(scope="module", params=list(PROFILES))
def drawn(request: pytest.FixtureRequest, annotated_sample: Callable[..., Path]) -> Drawn:
    name = PROFILES[request.param]
    return Drawn(SAMPLES / name, annotated_sample(name))  # the defaults: verification on


def test_each_loop_closure_draws_its_inliers_on_both_images_inside_them(drawn: Drawn) -> None:
    assert len(drawn.reported) > 20
    for record in drawn.reported:
        query, match = drawn.pairs(record)
        # Every inlier of the accepted check, up to the cap; one point per side of each.
        assert len(query) == len(match) == min(record.inliers, MAX_INLIER_POINTS) > 0
        for points, frame in ((query, record.query), (match, record.matched)):
            height, width = drawn.images[frame.log_time_ns].shape
            # Origin at the top left pixel's corner: a pixel's centre is half a pixel on.
            assert (points >= 0).all() and (points[:, 0] <= width).all()
            assert (points[:, 1] <= height).all()


def test_between_loop_closures_both_annotation_topics_are_empty(drawn: Drawn) -> None:
    queries = {r.query.log_time_ns for r in drawn.reported}
    times = {topic: [t for t, _ in messages] for topic, messages in drawn.topics.items()}
    # The match image's annotations come and go with the query image's.
    assert times[MATCH_ANNOTATIONS_TOPIC] == times[ANNOTATIONS_TOPIC]
    for frame in drawn.images:
        if frame in queries:
            continue
        for topic in drawn.topics:
            shown = drawn.at(topic, frame)
            assert (shown.points, shown.texts, shown.circles) == ([], [], []), (topic, frame)


def essential(record: LoopClosureRecord) -> F64:
    """E = [t]x R of the pair's recorded relative pose: x_match^T E x_query = 0."""
    rotation = Rotation.from_quat(record.rotation_xyzw).as_matrix()
    tx, ty, tz = record.translation_direction
    return np.array([[0, -tz, ty], [tz, 0, -tx], [-ty, tx, 0]]) @ rotation


def epipolar_distances(record: LoopClosureRecord, k: F64, query: F64, match: F64) -> F64:
    """Each match point's distance (pixels) from the epipolar line of its query point."""
    k_inv = np.linalg.inv(k)
    fundamental = k_inv.T @ essential(record) @ k_inv
    # Back to pixel centres at integers (the keypoints' convention, K's).
    q = np.column_stack([query - 0.5, np.ones(len(query))])
    m = np.column_stack([match - 0.5, np.ones(len(match))])
    lines = q @ fundamental.T
    return np.asarray(np.abs((m * lines).sum(axis=1)) / np.hypot(lines[:, 0], lines[:, 1]))


def test_the_points_satisfy_the_pairs_recorded_epipolar_geometry(
    annotated_sample: Callable[..., Path],
) -> None:
    """The ROS 2 sample (256 x 192 frames, enlarged to 320 for features): each pair's points
    lie within two pixels of the epipolar lines of the relative pose recorded on its message;
    the same points paired at random do not."""
    drawn = Drawn(SAMPLES / PROFILES["ros2"], annotated_sample(PROFILES["ros2"]))
    assert drawn.intrinsics is not None
    fx, fy, cx, cy = drawn.intrinsics
    k = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    rng = np.random.default_rng(0)
    posed = [r for r in drawn.reported if r.has_relative_pose]
    assert len(posed) > 20
    for record in posed:
        query, match = drawn.pairs(record)
        distances = epipolar_distances(record, k, query, match)
        assert np.median(distances) < 1.0 and np.percentile(distances, 95) < 2.0, record
        shuffled = epipolar_distances(record, k, query, match[rng.permutation(len(match))])
        assert np.median(shuffled) > 5.0, record


def patch(image: npt.NDArray[np.uint8], x: float, y: float, half: int) -> F64 | None:
    """The (2 half + 1)^2 pixels around a drawn point, normalised; None at the border."""
    col, row = int(x), int(y)  # the pixel the point lies in
    if not (half <= row < image.shape[0] - half and half <= col < image.shape[1] - half):
        return None
    window = image[row - half : row + half + 1, col - half : col + half + 1].astype(np.float64)
    spread = window.std()
    return None if spread < 1e-6 else (window - window.mean()) / spread


def mean_correlation(
    query_image: npt.NDArray[np.uint8],
    match_image: npt.NDArray[np.uint8],
    query: F64,
    match: F64,
) -> float:
    scores = []
    for (qx, qy), (mx, my) in zip(query, match, strict=True):
        a, b = patch(query_image, qx, qy, 3), patch(match_image, mx, my, 3)
        if a is not None and b is not None:
            scores.append(float((a * b).mean()))
    return float(np.mean(scores))


# 90 frames of 160 x 120 at 1 Hz, about two laps: small frames, enlarged twice for features.
SMALL_DRIVE = gen.Config(
    name="small", seed=11, route="loops", duration=90.0, rate=1.0, width=160, height=120,
    formats=("ros2mcap",),
)  # fmt: skip


@pytest.fixture(scope="module")
def small_drive(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Any]:
    folder = tmp_path_factory.mktemp("small-drive")
    gen.generate(replace(SMALL_DRIVE), folder, progress=False)
    log, output = folder / "small.ros2.mcap", folder / "small.annotated.mcap"
    result = annotate_log(log, output, Parameters(), AnnotateOptions())
    return log, output, result


def test_on_enlarged_small_frames_the_points_are_in_the_frames_own_pixels(
    small_drive: tuple[Path, Path, Any],
) -> None:
    """Features of 160 x 120 frames are detected at 320 x 240: the points drawn are mapped back
    (inside the frame, on its content: a patch around a query point looks like the patch
    around its match far more than like a random match point's)."""
    log, output, result = small_drive
    drawn = Drawn(log, output)
    assert len(drawn.reported) >= 3
    rng = np.random.default_rng(0)
    for record in drawn.reported:
        query, match = drawn.pairs(record)
        assert len(query) == min(record.inliers, MAX_INLIER_POINTS) > 0
        q_image = drawn.images[record.query.log_time_ns]
        m_image = drawn.images[record.matched.log_time_ns]
        assert q_image.shape == m_image.shape == (120, 160)
        for points in (query, match):
            assert (points >= 0).all() and (points <= [160, 120]).all()
        paired = mean_correlation(q_image, m_image, query, match)
        shuffled = mean_correlation(q_image, m_image, query, match[rng.permutation(len(match))])
        assert paired > 0.5 and paired > shuffled + 0.3, (record.query.index, paired, shuffled)
    # Only the reported pairs carry points through the run; rejected ones keep none.
    checks = [c for v in result.verification.decisions.values() for c in v.checks]
    assert any(not c.accepted for c in checks)
    assert all((c.verdict.inlier_points is not None) == c.accepted for c in checks)


def test_no_verify_draws_no_points_and_no_match_annotations(
    annotated_sample: Callable[..., Path],
) -> None:
    output = annotated_sample(PROFILES["json"], "--no-verify")
    with opened(output) as source:
        topics = {c.topic for c in source.channels()}
        texts = [json.loads(data) for _, data in source.raw_messages(ANNOTATIONS_TOPIC)]
    assert ANNOTATIONS_TOPIC in topics and MATCH_ANNOTATIONS_TOPIC not in topics
    assert {a["points"][0]["type"] for a in texts if a["points"]} == {2}  # the square alone
    assert all(len(a["points"]) <= 1 for a in texts)
