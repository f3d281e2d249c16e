"""annotate end to end: packed real frames in every container give evaluate's loop closures."""

from __future__ import annotations

import hashlib
import itertools
from pathlib import Path

import pytest
from mcap.reader import make_reader

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.cli.main import main
from doseqslam_logs.detector import Parameters, make_detector
from doseqslam_logs.pipeline.annotate import AnnotateOptions, annotate_log
from doseqslam_logs.pipeline.replay import replay
from doseqslam_logs.sources.image_folder import folder_frames, list_images
from loggen import pack_image_folder

pytestmark = pytest.mark.slow  # the pipeline runs in its fixtures (pyproject: markers)

FORMATS = ("ros2mcap", "foxglove", "bag", "db3")
PARAMS = Parameters(kappa_s=10.0)
PAPER = AnnotateOptions(verification=None)  # the detector alone: fast, and all these test
SAMPLE = Path(__file__).resolve().parents[1] / "sample_logs" / "drive_loops.ros2.mcap"


@pytest.fixture(scope="module")
def packed(shared_data, tmp_path_factory) -> dict[str, Path]:
    folder = shared_data / "rtabmap_samples_loop" / "images"
    out = tmp_path_factory.mktemp("packed")
    return dict(pack_image_folder.pack(folder, out, "rtabmap", 1.0, list(FORMATS)))


@pytest.fixture(scope="module")
def folder_pairs(shared_data) -> set[tuple[int, int]]:
    """What `evaluate --images` decides on the folder at 1 frame per second."""
    frames = folder_frames(shared_data / "rtabmap_samples_loop" / "images", 1.0)
    result = replay(frames, make_detector(PARAMS))
    return {(c.query_index, c.match_index) for d in result.decisions for c in d.loop_closures}


def test_packer_stores_the_original_bytes_at_one_second_spacing(shared_data) -> None:
    folder = shared_data / "rtabmap_samples_loop" / "images"
    frames = pack_image_folder.image_frames(folder, 1.0)
    assert [f.data for f in frames] == [p.read_bytes() for p in list_images(folder)]
    assert {b.stamp_ns - a.stamp_ns for a, b in itertools.pairwise(frames)} == {10**9}


@pytest.mark.parametrize("fmt", FORMATS)
def test_annotating_each_container_gives_the_folder_loop_closures(
    packed, folder_pairs, tmp_path, fmt
) -> None:
    out = tmp_path / "out.mcap"
    result = annotate_log(packed[fmt], out, PARAMS, PAPER)
    assert result.replay.frames == 84 and result.counts.skipped_total == 0
    log = read_annotations(out)
    pairs = {(m.query.index, m.match.index) for m in log.loop_closures}
    assert pairs == folder_pairs and len(pairs) >= 5
    assert len(log.sequences) == len(result.replay.decisions)
    assert log.metadata.parameters_hash == PARAMS.hash
    assert log.metadata.frames_used == 84 and log.metadata.feature_detector == "sift"


def test_output_is_byte_identical_and_the_input_untouched(packed, tmp_path) -> None:
    source = packed["ros2mcap"]
    before = hashlib.sha256(source.read_bytes()).hexdigest()
    a, b = tmp_path / "a.mcap", tmp_path / "b.mcap"
    annotate_log(source, a, PARAMS, PAPER)
    annotate_log(source, b, PARAMS, AnnotateOptions(workers=1, verification=None))
    assert a.read_bytes() == b.read_bytes()
    assert hashlib.sha256(source.read_bytes()).hexdigest() == before


def test_annotating_an_annotated_log_replaces_our_channels(packed, tmp_path) -> None:
    once, twice = tmp_path / "once.mcap", tmp_path / "twice.mcap"
    annotate_log(packed["ros2mcap"], once, PARAMS, PAPER)
    annotate_log(once, twice, PARAMS.replace(threshold=0.7), PAPER)
    with twice.open("rb") as stream:
        reader = make_reader(stream)
        topics = [c.topic for c in reader.get_summary().channels.values()]
        names = [m.name for m in reader.iter_metadata()]
        attachments = [a.name for a in reader.iter_attachments()]
    assert topics.count("/doseqslam/loop_closures") == 1 and names.count("doseqslam") == 1
    assert attachments.count("doseqslam/frame_times") == 1
    again = read_annotations(twice)
    assert again.parameters["threshold"] == 0.7
    assert all(m.f < 0.7 for m in again.loop_closures)


@pytest.mark.parametrize("fmt", ["bag", "foxglove"])
def test_frame_times_place_every_frame_index_in_time(packed, tmp_path, fmt) -> None:
    out = tmp_path / "out.mcap"
    annotate_log(packed[fmt], out, PARAMS, AnnotateOptions(sidecar=fmt == "bag", verification=None))
    times = read_annotations(out).frame_times
    assert times is not None and len(times) == 84
    # pack_image_folder spaces the frames one second apart and stamps them with the log time.
    assert (times.log_times_ns[1:] - times.log_times_ns[:-1] == 10**9).all()
    assert (times.header_stamps_ns == times.log_times_ns).all()


def test_ros2_output_reads_back_with_rosbags(packed, tmp_path) -> None:
    from rosbags.highlevel import AnyReader

    out = tmp_path / "out.mcap"
    annotate_log(packed["ros2mcap"], out, PARAMS, PAPER)
    with AnyReader([out]) as reader:
        ours = [c for c in reader.connections if c.topic == "/doseqslam/loop_closures"]
        msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(ours)]
    assert ours and len(msgs) >= 5 and all(m.f < 0.75 for m in msgs)


def test_cli_prints_a_summary_line(packed, tmp_path, capsys) -> None:
    out = tmp_path / "cli.mcap"
    code = main(["annotate", str(packed["bag"]), "-o", str(out), "--set", "kappa_s=10"])
    text = capsys.readouterr().out
    assert code == 0 and out.exists()
    assert "84 frames of /camera/image/compressed" in text and "loop closures" in text
    assert "frames/s" in text and "0 skipped frames" in text


@pytest.mark.parametrize("paper", [False, True])
def test_the_library_defaults_are_the_commands(paper, tmp_path, annotated_sample) -> None:
    """annotate_log(log, out) is `annotate LOG -o OUT`; with Parameters() and verification
    None it is `annotate --no-verify` (the command's output: the run's shared one)."""
    log = SAMPLE
    settings = (Parameters(), AnnotateOptions(verification=None)) if paper else ()
    result = annotate_log(log, tmp_path / "library.mcap", *settings)
    command = annotated_sample(log.name, *["--no-verify"] * paper)
    assert (tmp_path / "library.mcap").read_bytes() == command.read_bytes()
    assert (result.verification is None) is paper and result.loop_closures > 0
