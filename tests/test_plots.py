"""`evaluate OUT.mcap --plot DIR`: the pictures, and the difference matrix behind one of them."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from doseqslam_logs.annotations.reader import read_annotations
from doseqslam_logs.cli.main import main
from doseqslam_logs.detector import Parameters
from doseqslam_logs.evaluation.difference_matrix import difference_matrix
from doseqslam_logs.pipeline.annotate import AnnotateOptions, annotate_log

pytest.importorskip("matplotlib")
from matplotlib.figure import Figure
from matplotlib.image import imread

from doseqslam_logs.evaluation import plots

SAMPLES = Path(__file__).resolve().parents[1] / "sample_logs"
LOG = SAMPLES / "drive_loops.ros2.mcap"
GT = SAMPLES / "drive_loops.gt.npz"


@pytest.fixture(scope="module")
def annotated(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("plots") / "drive_loops.annotated.mcap"
    annotate_log(LOG, out, Parameters(), AnnotateOptions(verification=None))
    return out


def evaluate_json(capsys, *argv: object) -> dict:
    code = main(["evaluate", *(str(a) for a in argv), "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    return dict(json.loads(out))


def check_png(path: Path, min_bytes: int = 20_000) -> np.ndarray:
    """A PNG of a readable size with real content (not one flat colour)."""
    assert path.is_file() and min_bytes < path.stat().st_size < 300_000
    pixels = imread(path)
    height, width = pixels.shape[:2]
    assert height >= 500 and width >= 600
    assert pixels[..., :3].std() > 0.05
    return pixels


def test_three_pictures_with_pose_ground_truth(annotated, capsys, tmp_path) -> None:
    folder = tmp_path / "pictures"
    doc = evaluate_json(
        capsys, annotated, "--gt-topic", "/ground_truth/pose", "--radius", "2", "--plot", folder
    )
    names = ["pr_curve.png", "difference_matrix.png", "trajectory.png"]
    assert doc["plots"] == [str(folder / name) for name in names]
    for name in names:
        check_png(folder / name)
    assert sorted(p.name for p in folder.iterdir()) == sorted(names)  # no temporary left


def test_trajectory_from_another_topic_and_ground_truth_from_a_file(
    annotated, capsys, tmp_path
) -> None:
    doc = evaluate_json(capsys, annotated, "--gt", GT, "--poses-topic", "/odom", "--plot", tmp_path)
    assert [Path(p).name for p in doc["plots"]][-1] == "trajectory.png"
    check_png(tmp_path / "trajectory.png")


def test_no_pose_topic_no_trajectory(annotated, capsys, tmp_path) -> None:
    doc = evaluate_json(capsys, annotated, "--gt", GT, "--plot", tmp_path)
    assert [Path(p).name for p in doc["plots"]] == ["pr_curve.png", "difference_matrix.png"]
    assert not (tmp_path / "trajectory.png").exists()


def test_text_output_names_the_pictures(annotated, capsys, tmp_path) -> None:
    assert main(["evaluate", str(annotated), "--gt", str(GT), "--plot", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert f"wrote {tmp_path / 'pr_curve.png'}" in out


# -- what a person reads ------------------------------------------------------------------


@pytest.fixture
def figures(monkeypatch) -> dict[str, Figure]:
    """The Figures the CLI builds, by builder name (each still written as a PNG)."""
    built: dict[str, Figure] = {}

    def recording(name: str, build):
        def record(*args, **kwargs) -> Figure:
            built[name] = build(*args, **kwargs)
            return built[name]

        return record

    for name in ["pr_curve_figure", "difference_matrix_figure", "trajectory_figure"]:
        monkeypatch.setattr(plots, name, recording(name, getattr(plots, name)))
    return built


def test_titles_labels_and_legends(annotated, capsys, tmp_path, figures) -> None:
    evaluate_json(
        capsys, annotated, "--gt-topic", "/ground_truth/pose", "--radius", "2", "--plot", tmp_path
    )
    parameters_hash = read_annotations(annotated).metadata.parameters_hash
    assert len(parameters_hash) == 16
    assert sorted(figures) == ["difference_matrix_figure", "pr_curve_figure", "trajectory_figure"]
    labels = {
        "pr_curve_figure": ("recall", "precision"),
        "difference_matrix_figure": ("database frame (match index)", "query frame index"),
        "trajectory_figure": ("x (m)", "y (m)"),
    }
    for name, figure in figures.items():
        title = figure.get_suptitle()
        assert annotated.name in title, name
        assert "/camera/image/compressed" in title, name
        assert parameters_hash in title, name
        axes = figure.axes[0]
        assert axes.get_title(), name  # what the picture shows, under the run's title
        assert (axes.get_xlabel(), axes.get_ylabel()) == labels[name]
        legend = axes.get_legend()
        assert legend is not None, name
        assert all(text.get_text() for text in legend.get_texts()) and legend.get_texts(), name
    legend = figures["difference_matrix_figure"].axes[0].get_legend()
    assert legend is not None
    texts = [text.get_text() for text in legend.get_texts()]
    assert "ground-truth loop" in texts and any(t.startswith("loop closure, true") for t in texts)
    colourbar = figures["difference_matrix_figure"].axes[1]  # the colour bar's own axes
    assert colourbar.get_ylabel() == "enhanced difference"
    assert "/ground_truth/pose" in figures["trajectory_figure"].axes[0].get_title()


# -- the difference matrix ----------------------------------------------------------------


def test_subsampled_matrix_holds_the_full_matrixs_cells(annotated) -> None:
    log = read_annotations(annotated)
    full = difference_matrix(annotated, log, enhanced=False)
    assert full.values.shape == (240, 240) and full.stride == 1
    assert np.allclose(np.diag(full.values), 0.0) and np.allclose(full.values, full.values.T)
    small = difference_matrix(annotated, log, max_side=100, enhanced=False)
    assert small.stride == 3 and small.frame_indices.tolist() == list(range(0, 240, 3))
    picked = np.ix_(small.frame_indices, small.frame_indices)
    assert np.array_equal(small.values, full.values[picked])


def test_frames_found_by_time_or_by_decoding_agree(annotated) -> None:
    log = read_annotations(annotated)
    by_times = difference_matrix(annotated, log, max_side=60)
    older = replace(log, frame_times=None)  # an older annotation: every frame is decoded again
    by_decoding = difference_matrix(annotated, older, max_side=60)
    assert by_times.window == by_decoding.window == 10 and by_times.frames == 240
    assert np.array_equal(by_times.values, by_decoding.values)
    assert np.array_equal(by_times.frame_indices, by_decoding.frame_indices)
