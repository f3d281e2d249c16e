"""Ground-truth loading on the real matrices in shared/data, round trips and error cases."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io
from golden import RTABMAP_FRAMES, RTABMAP_LOOP_EVENTS
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import sparse

from doseqslam_logs.errors import GroundTruthError, UsageError
from doseqslam_logs.evaluation.groundtruth import GroundTruth, load_ground_truth

LIP6 = Path("lip6_outdoor/ground_truth")
KN_ZHANG = Path("loop_closure_gt_matrices/kn_zhang_lcd_eval")


# -- real files (numbers from the READMEs) ------------------------------------------------


@pytest.mark.parametrize(
    ("name", "variable", "nnz"),
    [
        ("Lip6OutdoorGroundTruth.mat", "truth", 3704),
        ("groundTruthLip6O.mat", "groundTruthMatrixLip6O", 19571),
    ],
)
def test_lip6_outdoor_matrices(shared_data: Path, name: str, variable: str, nnz: int) -> None:
    gt = load_ground_truth(shared_data / LIP6 / name)
    assert gt.n_frames == 1063
    assert gt.matrix.shape == (1063, 1063)
    assert gt.nnz == nnz
    assert gt.n_loop_events == 603
    rows = gt.query_rows()
    assert (rows[0], rows[-1], rows.size) == (460, 1062, 603)
    assert gt.variable == variable
    assert not gt.transposed
    assert gt.source.endswith(name)


def test_lip6_original_ground_truth_spot_checks(shared_data: Path) -> None:
    # The README's manual check: query 661 sees 199-203, query 1013 sees 85-89 and 551-555.
    gt = load_ground_truth(shared_data / LIP6 / "Lip6OutdoorGroundTruth.mat", variable="truth")
    assert [gt.is_true(661, j) for j in range(198, 205)] == [False] + [True] * 5 + [False]
    assert gt.matrix[[1013]].indices.tolist() == [85, 86, 87, 88, 89, 551, 552, 553, 554, 555]
    assert gt.is_true(661, 197, tolerance=2)
    assert not gt.is_true(661, 196, tolerance=2)


def test_tsintotas_lip6_is_a_superset_of_the_original(shared_data: Path) -> None:
    original = load_ground_truth(shared_data / LIP6 / "Lip6OutdoorGroundTruth.mat")
    wider = load_ground_truth(shared_data / LIP6 / "groundTruthLip6O.mat")
    coo = original.matrix.tocoo()
    assert wider.are_true(coo.row, coo.col).all()


def test_rtabmap_bitmap(shared_data: Path) -> None:
    gt = load_ground_truth(shared_data / "rtabmap_samples_loop" / "samples_GT.bmp")
    assert gt.n_frames == RTABMAP_FRAMES
    assert gt.nnz == 228
    assert gt.n_loop_events == RTABMAP_LOOP_EVENTS
    assert gt.variable is None and not gt.transposed
    coo = gt.matrix.tocoo()
    assert (coo.col < coo.row).all()


def test_upper_triangular_file_is_transposed(shared_data: Path) -> None:
    gt = load_ground_truth(shared_data / KN_ZHANG / "newcollege_GT.mat")
    assert gt.transposed
    assert gt.variable == "gt"
    assert gt.n_frames == 2624
    assert gt.nnz == 46753
    assert gt.n_loop_events == 1333
    coo = gt.matrix.tocoo()
    assert (coo.col < coo.row).all()  # now row = query (later) frame


# -- round trips through tmp_path ---------------------------------------------------------


def _example() -> np.ndarray:
    dense = np.zeros((6, 6), dtype=np.uint8)
    dense[4, 1] = dense[5, 1] = dense[5, 2] = 1
    return dense


def _assert_same(gt: GroundTruth, dense: np.ndarray) -> None:
    assert gt.n_frames == dense.shape[0]
    assert np.array_equal(gt.matrix.toarray(), dense != 0)


def test_npy_round_trip(tmp_path: Path) -> None:
    np.save(tmp_path / "gt.npy", _example())
    gt = load_ground_truth(tmp_path / "gt.npy")
    _assert_same(gt, _example())
    assert gt.query_rows().tolist() == [4, 5]
    assert gt.n_loop_events == 2


def test_npy_fortran_order_and_float(tmp_path: Path) -> None:
    dense = np.asfortranarray(_example().astype(np.float64) * 0.5)
    np.save(tmp_path / "gt.npy", dense)
    _assert_same(load_ground_truth(tmp_path / "gt.npy"), dense)


def test_npz_round_trip_with_variable_rule(tmp_path: Path) -> None:
    np.savez(tmp_path / "one.npz", loops=_example())
    one = load_ground_truth(tmp_path / "one.npz")
    _assert_same(one, _example())
    assert one.variable == "loops"
    np.savez(tmp_path / "two.npz", loops=_example(), other=np.eye(6))
    two = load_ground_truth(tmp_path / "two.npz", variable="loops")
    _assert_same(two, _example())


def test_mat_round_trip_dense_and_sparse(tmp_path: Path) -> None:
    scipy.io.savemat(tmp_path / "dense.mat", {"M": _example()})
    _assert_same(load_ground_truth(tmp_path / "dense.mat"), _example())
    scipy.io.savemat(tmp_path / "sparse.mat", {"S": sparse.csc_matrix(_example())})
    _assert_same(load_ground_truth(tmp_path / "sparse.mat"), _example())


def test_upper_triangular_npy_is_transposed(tmp_path: Path) -> None:
    np.save(tmp_path / "upper.npy", _example().T)
    gt = load_ground_truth(tmp_path / "upper.npy")
    assert gt.transposed
    _assert_same(gt, _example())


def test_ones_on_both_sides_are_kept(tmp_path: Path) -> None:
    dense = _example()
    dense[0, 3] = 1
    np.save(tmp_path / "both.npy", dense)
    gt = load_ground_truth(tmp_path / "both.npy")
    assert not gt.transposed
    _assert_same(gt, dense)


def test_colour_png_any_channel_counts(tmp_path: Path) -> None:
    image = np.zeros((5, 5, 3), dtype=np.uint8)
    image[3, 1, 2] = 255  # only the red channel (BGR order)
    image[4, 0, 0] = 1
    cv2.imwrite(str(tmp_path / "gt.png"), image)
    gt = load_ground_truth(tmp_path / "gt.png")
    assert sorted(zip(*gt.matrix.nonzero(), strict=True)) == [(3, 1), (4, 0)]


# -- error cases --------------------------------------------------------------------------


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(GroundTruthError, match=r"absent\.mat: ground-truth file not found"):
        load_ground_truth(tmp_path / "absent.mat")


def test_not_square(tmp_path: Path) -> None:
    np.save(tmp_path / "wide.npy", np.zeros((3, 4)))
    with pytest.raises(GroundTruthError, match=r"wide\.npy: .*square matrix, got 3x4"):
        load_ground_truth(tmp_path / "wide.npy")
    np.save(tmp_path / "cube.npy", np.zeros((2, 2, 2)))
    with pytest.raises(GroundTruthError, match="square matrix"):
        load_ground_truth(tmp_path / "cube.npy")


def test_ambiguous_variable_lists_them(tmp_path: Path) -> None:
    scipy.io.savemat(tmp_path / "two.mat", {"alpha": np.eye(3), "beta": np.eye(3)})
    with pytest.raises(GroundTruthError, match=r"two\.mat: holds several variables \(alpha, beta"):
        load_ground_truth(tmp_path / "two.mat")
    np.savez(tmp_path / "two.npz", a=np.eye(3), b=np.eye(3))
    with pytest.raises(GroundTruthError, match="several variables"):
        load_ground_truth(tmp_path / "two.npz")


def test_missing_variable_lists_available(tmp_path: Path) -> None:
    scipy.io.savemat(tmp_path / "one.mat", {"alpha": np.eye(3)})
    with pytest.raises(GroundTruthError, match=r"no variable 'gamma'; available: alpha"):
        load_ground_truth(tmp_path / "one.mat", variable="gamma")


def test_empty_npz_has_no_variable(tmp_path: Path) -> None:
    np.savez(tmp_path / "empty.npz")
    with pytest.raises(GroundTruthError, match="holds no variable"):
        load_ground_truth(tmp_path / "empty.npz")


def test_wrong_extension(tmp_path: Path) -> None:
    (tmp_path / "gt.txt").write_text("0 1\n1 0\n")
    with pytest.raises(GroundTruthError, match=r"gt\.txt: unsupported ground-truth format"):
        load_ground_truth(tmp_path / "gt.txt")


def test_variable_with_a_format_that_has_none(tmp_path: Path) -> None:
    np.save(tmp_path / "gt.npy", np.eye(3))
    with pytest.raises(GroundTruthError, match=r"only applies to \.mat and \.npz"):
        load_ground_truth(tmp_path / "gt.npy", variable="x")


@pytest.mark.parametrize("name", ["junk.mat", "junk.npy", "junk.npz", "junk.png", "junk.bmp"])
def test_corrupt_files(tmp_path: Path, name: str) -> None:
    (tmp_path / name).write_bytes(b"this is not a matrix at all" * 10)
    with pytest.raises(GroundTruthError, match=name.replace(".", r"\.")):
        load_ground_truth(tmp_path / name)


def test_non_numeric_matrix(tmp_path: Path) -> None:
    np.save(tmp_path / "text.npy", np.array([["a", "b"], ["c", "d"]]))
    with pytest.raises(GroundTruthError, match="numeric"):
        load_ground_truth(tmp_path / "text.npy")


# -- constructors and look-ups ------------------------------------------------------------


def test_from_pairs_and_lookups() -> None:
    gt = GroundTruth.from_pairs(10, [(5, 1), (6, 2), (6, 2), (9, 4)])
    assert gt.nnz == 3  # the duplicate is merged
    assert gt.query_rows().tolist() == [5, 6, 9]
    assert gt.is_true(5, 1) and not gt.is_true(5, 2)
    assert gt.is_true(5, 2, tolerance=1)
    assert gt.are_true([5, 6, 9, 9], [0, 2, 4, 9], tolerance=0).tolist() == [
        False,
        True,
        True,
        False,
    ]


def test_tolerance_window_stays_in_its_row() -> None:
    # A one at the end of row 4 must not leak into the start of row 5 through the flat keys.
    gt = GroundTruth.from_pairs(10, [(4, 9)])
    assert not gt.is_true(5, 0, tolerance=3)
    assert gt.is_true(4, 9, tolerance=3) and gt.is_true(4, 6, tolerance=3)


def test_lookup_errors() -> None:
    gt = GroundTruth.from_pairs(10, [(5, 1)])
    with pytest.raises(GroundTruthError, match="outside the ground truth's 10 frames"):
        gt.is_true(10, 1)
    with pytest.raises(GroundTruthError, match="outside"):
        gt.are_true([5], [-1])
    with pytest.raises(UsageError, match="tolerance"):
        gt.is_true(5, 1, tolerance=-1)
    with pytest.raises(GroundTruthError, match="outside the 10 x 10"):
        GroundTruth.from_pairs(10, [(10, 0)])


def test_from_dense_keeps_orientation_unless_asked() -> None:
    upper = _example().T
    assert not GroundTruth.from_dense(upper).transposed
    assert GroundTruth.from_dense(upper, auto_transpose=True).transposed


def test_a_36000_frame_ground_truth_stays_small() -> None:
    n = 36_000
    queries = np.arange(5_000, n)
    pairs = np.stack(
        [np.repeat(queries, 3), np.repeat(queries - 4_000, 3) + np.tile([-1, 0, 1], queries.size)],
        axis=1,
    )
    tracemalloc.start()
    gt = GroundTruth.from_pairs(n, pairs)
    hits = gt.are_true(pairs[:, 0], pairs[:, 1], tolerance=5)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert hits.all() and gt.n_loop_events == queries.size
    assert peak < 50 * 2**20  # a dense bool matrix would be 1.3 GB


def test_npy_is_scanned_without_a_full_copy(tmp_path: Path) -> None:
    dense = np.zeros((6_000, 6_000), dtype=np.uint8)  # 36 MB on disk
    dense[np.arange(1, 6_000), np.arange(5_999)] = 1
    np.save(tmp_path / "big.npy", dense)
    del dense
    tracemalloc.start()
    gt = load_ground_truth(tmp_path / "big.npy")
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert gt.nnz == 5_999
    assert peak < 8 * 2**20  # np.load without mmap would take 36 MB


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(1, 25),
    cells=st.lists(st.tuples(st.integers(0, 24), st.integers(0, 24)), max_size=40),
    probes=st.lists(st.tuples(st.integers(0, 24), st.integers(0, 24)), max_size=30),
    tolerance=st.integers(0, 4),
)
def test_are_true_matches_a_dense_scan(
    n: int,
    cells: list[tuple[int, int]],
    probes: list[tuple[int, int]],
    tolerance: int,
) -> None:
    dense = np.zeros((n, n), dtype=bool)
    for q, m in cells:
        if q < n and m < n:
            dense[q, m] = True
    gt = GroundTruth.from_dense(dense)
    inside = [(q, m) for q, m in probes if q < n and m < n]
    expected = [dense[q, max(0, m - tolerance) : m + tolerance + 1].any() for q, m in inside]
    got = gt.are_true([q for q, _ in inside], [m for _, m in inside], tolerance)
    assert got.tolist() == expected
    assert gt.query_rows().tolist() == np.flatnonzero(dense.any(axis=1)).tolist()


def test_scipy_sparse_npz_round_trip(tmp_path) -> None:
    """Large ground truths (hour-long logs) are saved with scipy.sparse.save_npz."""
    from scipy import sparse

    matrix = sparse.csr_matrix(([1, 1, 1], ([5, 9, 9], [1, 2, 3])), shape=(36000, 36000))
    path = tmp_path / "big_gt.npz"
    sparse.save_npz(path, matrix)
    gt = load_ground_truth(path)
    assert gt.n_frames == 36000 and gt.n_loop_events == 2
    assert gt.is_true(9, 3) and not gt.is_true(9, 4) and gt.is_true(9, 4, tolerance=1)
