"""The ROS encoders build sequences of flat types (points, colours) straight from their dicts
(`RosBuilder._flat_items`): the bytes must be those of the generic builder, in both ROS
versions, and a malformed item must still fail with the builder's error."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from doseqslam_logs.sinks import visualization as vis
from doseqslam_logs.sinks.visual_encoders import (
    Dots,
    Lines,
    Ros1VisualEncoder,
    Ros2VisualEncoder,
)

ENCODERS = {"ros1": Ros1VisualEncoder(), "ros2": Ros2VisualEncoder()}
coordinate = st.floats(allow_nan=False, allow_infinity=False, width=64)
point3 = st.tuples(coordinate, coordinate, coordinate)
point2 = st.tuples(coordinate, coordinate)


@contextlib.contextmanager
def _generic(encoder: Ros1VisualEncoder | Ros2VisualEncoder) -> Iterator[None]:
    """The encoder with the flat path off: every item through `build`."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(encoder, "_is_flat", lambda typename: False)
        yield


@settings(max_examples=40, deadline=None)
@given(
    version=st.sampled_from(sorted(ENCODERS)),
    points=st.lists(point3, max_size=40),
    dots=st.lists(point2, max_size=40),
    time_ns=st.integers(0, 2**31 * 10**9 - 1),  # ROS 1 seconds are int32
)
def test_flat_items_encode_the_bytes_of_the_generic_builder(
    version: str, points: list[tuple[float, float, float]], dots, time_ns: int
) -> None:
    encoder = ENCODERS[version]
    lines = Lines("doseqslam/loop_closures", 3, vis.LINE_LIST, points, vis.LOOP_COLOR, 0.08)
    marked = Dots(dots, vis.INLIER_COLOR, vis.INLIER_RADIUS_PX)
    fast = encoder.scene("map", time_ns, [lines]), encoder.annotations(time_ns, [], [], [marked])
    with _generic(encoder):
        generic = (
            encoder.scene("map", time_ns, [lines]),
            encoder.annotations(time_ns, [], [], [marked]),
        )
    assert fast == generic


def test_the_flat_path_takes_points_and_colours_but_not_times() -> None:
    encoder = ENCODERS["ros2"]
    assert encoder._is_flat("geometry_msgs/msg/Point")
    assert encoder._is_flat("std_msgs/msg/ColorRGBA")
    assert not encoder._is_flat("builtin_interfaces/msg/Time")  # our dicts spell it otherwise
    assert not encoder._is_flat("std_msgs/msg/Header")  # a stamp and a string: not all base


@pytest.mark.parametrize(
    ("item", "error"),
    [
        ({"x": 1.0, "y": 2.0}, "missing fields ['z'], unknown fields []"),
        ({"x": 1.0, "y": 2.0, "z": 0.0, "w": 1.0}, "missing fields [], unknown fields ['w']"),
    ],
)
def test_a_malformed_point_fails_with_the_builders_error(
    item: dict[str, float], error: str
) -> None:
    encoder = ENCODERS["ros2"]
    good = {"x": 0.0, "y": 0.0, "z": 0.0}
    with pytest.raises(ValueError) as failed:
        encoder._flat_items("geometry_msgs/msg/Point", [good, item])
    assert str(failed.value) == f"geometry_msgs/msg/Point: {error}"
