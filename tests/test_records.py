"""The typed records of our channels: what the writer builds reads back the same, and logs
written by older versions (fewer fields) read with the documented "not recorded" values."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_sinks import PARAMETERS_HASH, make_decisions, make_frame_times

from doseqslam_logs.annotations.reader import plain, read_annotations
from doseqslam_logs.annotations.records import (
    NOT_RECORDED,
    FrameRef,
    FrameTimes,
    LoopClosureRecord,
    RunMetadata,
    SequenceRecord,
)
from doseqslam_logs.annotations.writer import loop_closure_messages, sequence_messages
from doseqslam_logs.pipeline.annotate import AnnotateOptions, annotate_log
from doseqslam_logs.verification import DEFAULT_VERIFICATION

# The fields of the first LoopClosure definition (0.1): everything later was appended.
FIRST_LOOP_CLOSURE_FIELDS = 21
FIRST_SEQUENCE_FIELDS = 24
SAMPLE = Path(__file__).resolve().parent.parent / "sample_logs" / "drive_parked.ros2.mcap"


def built() -> tuple[list[LoopClosureRecord], list[SequenceRecord]]:
    times = make_frame_times(7 * 10**9)
    closures = loop_closure_messages(make_decisions(), times, "doseqslam", PARAMETERS_HASH)
    sequences = sequence_messages(make_decisions(), times, "doseqslam", PARAMETERS_HASH)
    return (
        [m.record for m in closures if isinstance(m.record, LoopClosureRecord)],
        [m.record for m in sequences if isinstance(m.record, SequenceRecord)],
    )


def test_records_read_back_as_written() -> None:
    closures, sequences = built()
    assert closures and sequences
    for lc in closures:  # repr: NaN (a missing float) is not equal to itself
        assert repr(LoopClosureRecord.from_message(lc.to_message())) == repr(lc)
    for s in sequences:
        assert repr(SequenceRecord.from_message(s.to_message())) == repr(s)


def test_a_loop_closure_of_an_older_version_reads_as_not_recorded() -> None:
    closures, _ = built()
    full = closures[0].to_message()
    first = dict(list(full.items())[:FIRST_LOOP_CLOSURE_FIELDS])
    assert list(first)[-1] == "parameters_hash"
    old = LoopClosureRecord.from_message(first)
    assert old.verification == NOT_RECORDED and old.reported
    assert old.matched == old.match and old.proposal_match_index == old.match.index
    assert not old.has_relative_pose and math.isnan(old.rotation_deg)
    with pytest.raises(KeyError):
        LoopClosureRecord.from_message({k: v for k, v in first.items() if k != "sequence_id"})


def test_a_sequence_of_an_older_version_reads_as_not_recorded() -> None:
    _, sequences = built()
    full = sequences[2].to_message()
    first = dict(list(full.items())[:FIRST_SEQUENCE_FIELDS])
    assert list(first)[-1] == "parameters_hash"
    old = SequenceRecord.from_message(first)
    assert old.verification == NOT_RECORDED and old.verified_pairs == 0
    assert old.candidate_query_indices == sequences[2].candidate_query_indices


@settings(max_examples=50, deadline=None)
@given(
    index=st.integers(0, 2**40),
    log_time=st.integers(0, 2**63 - 1),
    stamp=st.none() | st.just(0) | st.integers(0, 2**63 - 1),
)
def test_frame_refs_round_trip(index: int, log_time: int, stamp: int | None) -> None:
    frame = FrameRef(index, log_time, stamp)
    assert FrameRef.from_message(frame.message_fields("x"), "x") == frame
    # The detector's rule (pipeline.decode.frame_time): no stamp, or a stamp of 0, is log time.
    assert frame.time_ns == (stamp if stamp else log_time)
    times = FrameTimes.from_pairs([(log_time, stamp)])
    assert times.detector_times_ns("header").tolist() == [frame.time_ns]
    assert times.detector_times_ns("log").tolist() == [log_time]


@pytest.mark.slow
@pytest.mark.parametrize("verification", [None, DEFAULT_VERIFICATION])
def test_run_metadata_reads_back_the_entries_it_wrote(tmp_path: Path, verification) -> None:
    out = tmp_path / "out.mcap"
    annotate_log(SAMPLE, out, options=AnnotateOptions(verification=verification))
    meta = read_annotations(out).metadata
    assert meta.to_entries() == meta.recorded  # the same keys, values and order
    assert list(meta.to_entries()) == list(meta.recorded)
    assert meta.verification == ("off" if verification is None else "on")
    assert meta.image_topic == "/camera/image/compressed" and meta.frames_used > 0
    assert (meta.verified_pairs > 0) == (verification is not None)


def test_metadata_of_an_older_version_takes_defaults() -> None:
    entries = {"tool_version": "0.1.0", "parameters": '{"threshold": 0.75}', "frames_used": "84"}
    meta = RunMetadata.from_entries(entries)
    assert meta.frames_used == 84 and meta.verification == "off" and meta.start_ns is None
    assert meta.odometry_topic == ""  # not recorded: export and optimize take the log's rule
    assert meta.parameters == {"threshold": 0.75} and meta.recorded == entries
    with pytest.raises(ValueError):
        RunMetadata.from_entries({**entries, "frames_used": "many"})


@pytest.mark.parametrize("profile", ["ros2", "ros1", ""])
def test_metric_fields_round_trip_in_every_profile(profile: str) -> None:
    """A rotation-only pose's infinite translation variances survive every encoding (JSON:
    written as 1e999, read back as infinity); its NaN translation reads back as NaN."""
    from doseqslam_logs.annotations.records import LOOP_CLOSURE
    from doseqslam_logs.sinks.encoders import encoder_for_profile

    covariance = [0.0] * 36
    for i in range(3):
        covariance[7 * i] = math.inf
        covariance[7 * (i + 3)] = 1e-4 * (i + 1)
    closures, _ = built()
    record = dataclasses.replace(
        closures[0],
        metric_method="rotation_only",
        metric_rotation_xyzw=(0.0, 0.1, 0.0, math.sqrt(0.99)),
        metric_covariance=tuple(covariance),
        metric_inliers=40,
        metric_residual_px=0.7,
        metric_reason="depth_pnp: no depth topic; odometry_pnp: no odometry topic",
    )
    encoder = encoder_for_profile(profile)
    data = encoder.encode(LOOP_CLOSURE, record.to_message())
    if profile == "":
        message = json.loads(data)
        assert "metric_translation" not in message  # NaN: omitted, as every float
        assert b"1e999" in data
    else:
        message = _ros_message(profile, encoder, data)
    back = LoopClosureRecord.from_message(message)
    assert repr(back) == repr(record)
    assert np.isinf(np.diagonal(back.metric_covariance_matrix())[:3]).all()


def _ros_message(profile: str, encoder: object, data: bytes) -> dict[str, object]:
    """A ROS message decoded with rosbags, as the plain dict the reader gives."""
    from doseqslam_logs.annotations.records import LOOP_CLOSURE

    typename = encoder.typename(LOOP_CLOSURE)  # type: ignore[attr-defined]
    store = encoder.typestore  # type: ignore[attr-defined]
    if profile == "ros2":
        decoded = store.deserialize_cdr(data, typename)
    else:
        decoded = store.deserialize_ros1(data, typename)
    return plain(decoded)  # type: ignore[no-any-return]
