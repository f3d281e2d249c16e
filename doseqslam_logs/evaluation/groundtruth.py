"""Ground-truth loop matrices: loading (.mat, .npy, .npz, .bmp, .png) and sparse look-ups.

`LoopTruth` is what scoring asks of a ground truth; `GroundTruth` (a matrix, every loop cell
held) and `pose_ground_truth.PoseGroundTruth` (answered from poses) both provide it.
"""

from __future__ import annotations

import os
import zipfile
import zlib
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np
import numpy.typing as npt
import scipy.io
from scipy import sparse
from scipy.io.matlab import MatReadError

from ..errors import GroundTruthError, UsageError
from ..sources import opencv_quiet  # noqa: F401 - OpenCV's log off, once

IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

# Dense matrices are scanned in row blocks of about this many bytes, so that a large
# memory-mapped .npy is never copied whole into memory.
_BLOCK_BYTES = 1 << 23

_IN_MEMORY = "<memory>"


class LoopTruth(Protocol):
    """Which frame pairs are loops: what the metrics, the plots and `diff` ask of a ground
    truth. Rows are query (later) frames, columns earlier ones."""

    source: str
    transposed: bool  # read transposed from its file (see `load_ground_truth`)

    @property
    def n_frames(self) -> int:
        """N, the frames covered."""
        ...

    @property
    def nnz(self) -> int:
        """Number of loop cells."""
        ...

    @property
    def n_loop_events(self) -> int:
        """Query frames with at least one loop: the recall denominator."""
        ...

    def query_rows(self) -> IntArray:
        """Sorted query frames with at least one loop."""
        ...

    def is_true(self, query: int, match: int, tolerance: int = 0) -> bool:
        """Whether (query, match +- tolerance) holds a loop cell."""
        ...

    def are_true(
        self, queries: npt.ArrayLike, matches: npt.ArrayLike, tolerance: int = 0
    ) -> BoolArray:
        """`is_true` of each (queries[i], matches[i])."""
        ...

    def cell_batches(self) -> Iterator[tuple[IntArray, IntArray]]:
        """(rows, columns) of every loop cell, a bounded batch at a time."""
        ...


class GroundTruth:
    """An N x N boolean loop matrix: row = query (later) frame, column = earlier frame.

    Stored as scipy.sparse CSR plus a sorted array of flat cell keys (row * N + column), so that
    memory grows with the number of ones, never with N * N. Build one with `load_ground_truth`,
    `GroundTruth.from_dense`, `GroundTruth.from_pairs` or `GroundTruth.from_sparse`.

    Attributes:
        source: the file it was read from (or "<memory>").
        variable: the variable read from a .mat/.npz file, else None.
        transposed: True when the stored matrix was upper triangular and was transposed on load.
    """

    def __init__(
        self,
        n_frames: int,
        rows: npt.ArrayLike,
        cols: npt.ArrayLike,
        *,
        source: str = _IN_MEMORY,
        variable: str | None = None,
        transposed: bool = False,
    ) -> None:
        """Build from the (row, column) coordinates of the ones; duplicates are merged.

        Raises:
            GroundTruthError: a coordinate lies outside the N x N matrix.
        """
        n = int(n_frames)
        r = np.asarray(rows, dtype=np.int64).ravel()
        c = np.asarray(cols, dtype=np.int64).ravel()
        if n < 0 or r.shape != c.shape:
            raise GroundTruthError(f"{source}: invalid ground-truth coordinates")
        if r.size and (min(r.min(), c.min()) < 0 or max(r.max(), c.max()) >= n):
            raise GroundTruthError(f"{source}: a loop cell lies outside the {n} x {n} matrix")
        # Flat keys sorted in row-major order double as the CSR layout and the search index.
        self._keys: IntArray = np.unique(r * n + c)
        self._n = n
        self.source = source
        self.variable = variable
        self.transposed = transposed
        indptr = np.searchsorted(self._keys // max(n, 1), np.arange(n + 1), side="left")
        self._matrix = sparse.csr_array(
            (np.ones(self._keys.size, dtype=bool), self._keys % max(n, 1), indptr), shape=(n, n)
        )

    # -- constructors ---------------------------------------------------------------------

    @classmethod
    def from_dense(
        cls, matrix: npt.ArrayLike, *, source: str = _IN_MEMORY, auto_transpose: bool = False
    ) -> GroundTruth:
        """Build from a dense square matrix; any non-zero cell is a loop.

        With `auto_transpose`, a matrix whose ones all lie above the diagonal is transposed
        (as `load_ground_truth` does); otherwise it is taken as row = query.

        Raises:
            GroundTruthError: the matrix is not 2-D and square, or not numeric.
        """
        return _build(np.asarray(matrix), source, None, auto_transpose)

    @classmethod
    def from_sparse(
        cls, matrix: Any, *, source: str = _IN_MEMORY, auto_transpose: bool = False
    ) -> GroundTruth:
        """Build from a scipy.sparse square matrix; any stored non-zero is a loop.

        Raises:
            GroundTruthError: the matrix is not square.
        """
        return _build(matrix, source, None, auto_transpose)

    @classmethod
    def from_pairs(
        cls,
        n: int,
        pairs: Iterable[tuple[int, int]] | npt.NDArray[np.integer[Any]],
        *,
        source: str = _IN_MEMORY,
    ) -> GroundTruth:
        """Build an n x n matrix with ones at the given (query, match) pairs.

        Raises:
            GroundTruthError: the pairs are not (query, match) couples or lie outside n x n.
        """
        try:
            coords = np.asarray(pairs if isinstance(pairs, np.ndarray) else list(pairs), np.int64)
        except (TypeError, ValueError) as exc:
            raise GroundTruthError(f"{source}: pairs must be (query, match) couples") from exc
        if coords.size == 0:
            coords = coords.reshape(0, 2)
        if coords.ndim != 2 or coords.shape[1] != 2:
            raise GroundTruthError(f"{source}: pairs must be (query, match) couples")
        return cls(n, coords[:, 0], coords[:, 1], source=source)

    # -- queries --------------------------------------------------------------------------

    @property
    def n_frames(self) -> int:
        """N, the number of frames the matrix covers."""
        return self._n

    @property
    def nnz(self) -> int:
        """Number of loop cells (ones)."""
        return int(self._keys.size)

    @property
    def matrix(self) -> Any:
        """The loop matrix as a boolean `scipy.sparse.csr_array` (do not modify it)."""
        return self._matrix

    def cell_batches(self) -> Iterator[tuple[IntArray, IntArray]]:
        """(rows, columns) of the loop cells: one batch, as they are all held anyway."""
        n = max(self._n, 1)
        yield self._keys // n, self._keys % n

    def query_rows(self) -> IntArray:
        """Sorted indices of the rows (query frames) that have at least one loop cell."""
        return np.flatnonzero(np.diff(self._matrix.indptr) > 0).astype(np.int64)

    @property
    def n_loop_events(self) -> int:
        """Number of query frames with at least one loop: the recall denominator."""
        return int(np.count_nonzero(np.diff(self._matrix.indptr)))

    def is_true(self, query: int, match: int, tolerance: int = 0) -> bool:
        """True when any GT[query, match - tolerance .. match + tolerance] is a loop cell.

        Raises:
            GroundTruthError: query or match lies outside the matrix.
            UsageError: tolerance is negative.
        """
        return bool(self.are_true([query], [match], tolerance)[0])

    def are_true(
        self, queries: npt.ArrayLike, matches: npt.ArrayLike, tolerance: int = 0
    ) -> BoolArray:
        """Vectorized `is_true`: one boolean per (queries[i], matches[i]) pair.

        Two binary searches per pair over the sorted cell keys, so O(K log nnz) for K pairs.

        Raises:
            GroundTruthError: an index lies outside the matrix, or the arrays differ in shape.
            UsageError: tolerance is negative.
        """
        q, m = checked_pairs(self.source, self._n, queries, matches, tolerance)
        n = self._n
        # Clip the window to the row so that it never spills into the neighbouring rows' keys.
        low = q * n + np.maximum(m - tolerance, 0)
        high = q * n + np.minimum(m + tolerance, n - 1)
        first = np.searchsorted(self._keys, low, side="left")
        after = np.searchsorted(self._keys, high, side="right")
        result: BoolArray = after > first
        return result

    def __repr__(self) -> str:
        return (
            f"GroundTruth(source={self.source!r}, n_frames={self._n}, nnz={self.nnz}, "
            f"loop_events={self.n_loop_events}, transposed={self.transposed})"
        )


def checked_pairs(
    source: str, n: int, queries: npt.ArrayLike, matches: npt.ArrayLike, tolerance: int
) -> tuple[IntArray, IntArray]:
    """(queries, matches) as int64 arrays, checked against a ground truth of n frames.

    Raises:
        GroundTruthError: an index lies outside the n frames, or the arrays differ in shape.
        UsageError: tolerance is negative.
    """
    q = np.asarray(queries, dtype=np.int64).ravel()
    m = np.asarray(matches, dtype=np.int64).ravel()
    if q.shape != m.shape:
        raise GroundTruthError(f"{source}: {q.size} queries but {m.size} matches")
    if tolerance < 0:
        raise UsageError(f"tolerance must be >= 0, got {tolerance}")
    if q.size:
        lowest = min(int(q.min()), int(m.min()))
        highest = max(int(q.max()), int(m.max()))
        if lowest < 0 or highest >= n:
            bad = lowest if lowest < 0 else highest
            raise GroundTruthError(
                f"{source}: frame index {bad} is outside the ground truth's {n} frames"
            )
    return q, m


# -- loading ------------------------------------------------------------------------------


def load_ground_truth(path: str | os.PathLike[str], variable: str | None = None) -> GroundTruth:
    """Read a ground-truth loop matrix; any non-zero cell is a loop.

    Formats (by extension, case-insensitive): MATLAB v5 `.mat` (scipy.io.loadmat), `.npy`
    (memory-mapped), `.npz`, and 8-bit `.bmp` / `.png` bitmaps (colour: any channel non-zero).
    For `.mat` and `.npz`, `variable` names the matrix; without it the file must hold exactly
    one (non-dunder) variable. A matrix with ones only above the diagonal is transposed so that
    rows are query frames, and `GroundTruth.transposed` says so.

    Raises:
        GroundTruthError: the file is missing, unreadable, of an unsupported type, holds no or
            several candidate variables, lacks the named variable, or the matrix is not square.
    """
    file = Path(path)
    if not file.is_file():
        raise GroundTruthError(f"{file}: ground-truth file not found")
    loader = _LOADERS.get(file.suffix.lower())
    if loader is None:
        raise GroundTruthError(
            f"{file}: unsupported ground-truth format {file.suffix!r} "
            f"(expected one of {', '.join(sorted(_LOADERS))})"
        )
    if variable is not None and file.suffix.lower() not in (".mat", ".npz"):
        raise GroundTruthError(f"{file}: a variable name only applies to .mat and .npz files")
    matrix, chosen = loader(file, variable)
    return _build(matrix, str(file), chosen, auto_transpose=True)


def _pick_variable(file: Path, names: list[str], variable: str | None) -> str:
    """Apply the variable rule: the named one, else the only one."""
    if variable is not None:
        if variable not in names:
            raise GroundTruthError(
                f"{file}: no variable {variable!r}; available: {', '.join(names) or 'none'}"
            )
        return variable
    if len(names) != 1:
        problem = "holds no variable" if not names else "holds several variables"
        raise GroundTruthError(
            f"{file}: {problem} ({', '.join(names) or '-'}); name the one to use"
        )
    return names[0]


def _load_mat(file: Path, variable: str | None) -> tuple[Any, str]:
    # scipy raises a spread of exception types on corrupt or foreign files.
    try:
        names = [name for name, _, _ in scipy.io.whosmat(file) if not name.startswith("__")]
        chosen = _pick_variable(file, names, variable)
        # Load only the chosen variable: other variables may be large.
        return scipy.io.loadmat(file, variable_names=[chosen])[chosen], chosen
    except NotImplementedError as exc:  # MATLAB v7.3 files are HDF5
        raise GroundTruthError(f"{file}: unsupported .mat version ({exc}); save with -v7") from exc
    except (MatReadError, ValueError, TypeError, OSError, EOFError, zlib.error) as exc:
        raise GroundTruthError(f"{file}: not a readable MATLAB file ({exc})") from exc


def _load_npy(file: Path, variable: str | None) -> tuple[Any, None]:
    try:
        # Memory-mapped: only the row blocks being scanned are paged in.
        return np.load(file, mmap_mode="r", allow_pickle=False), None
    except (ValueError, OSError, EOFError) as exc:
        raise GroundTruthError(f"{file}: not a readable .npy array ({exc})") from exc


# The arrays scipy.sparse.save_npz writes: such a file holds one sparse matrix.
_SPARSE_NPZ_KEYS = {"format", "shape", "data"}


def _load_npz(file: Path, variable: str | None) -> tuple[Any, str]:
    try:
        with np.load(file, allow_pickle=False) as archive:
            if set(archive.files) >= _SPARSE_NPZ_KEYS and variable is None:
                return sparse.load_npz(file), "sparse"
            chosen = _pick_variable(file, list(archive.files), variable)
            return archive[chosen], chosen
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
        raise GroundTruthError(f"{file}: not a readable .npz archive ({exc})") from exc


def _load_bitmap(file: Path, variable: str | None) -> tuple[Any, None]:
    image = cv2.imread(str(file), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise GroundTruthError(f"{file}: not a readable image")
    # Colour (or grey + alpha): a loop is any non-zero channel.
    return (image.any(axis=2) if image.ndim == 3 else image), None


_Loader = Callable[[Path, str | None], tuple[Any, str | None]]
_LOADERS: dict[str, _Loader] = {
    ".mat": _load_mat,
    ".npy": _load_npy,
    ".npz": _load_npz,
    ".bmp": _load_bitmap,
    ".png": _load_bitmap,
}


def _build(matrix: Any, source: str, variable: str | None, auto_transpose: bool) -> GroundTruth:
    """Validate shape and type, extract the ones, fix the orientation."""
    shape = tuple(getattr(matrix, "shape", ()))
    if len(shape) != 2 or shape[0] != shape[1]:
        what = "x".join(str(s) for s in shape) or "a scalar"
        raise GroundTruthError(f"{source}: ground truth must be a square matrix, got {what}")
    if sparse.issparse(matrix):
        coo = sparse.coo_array(matrix)
        _refuse_non_finite(coo.data, source)
        keep = coo.data != 0
        rows, cols = coo.row[keep].astype(np.int64), coo.col[keep].astype(np.int64)
    else:
        if matrix.dtype.kind not in "biuf":
            raise GroundTruthError(f"{source}: ground truth must be numeric, got {matrix.dtype}")
        _refuse_non_finite(matrix, source)
        rows, cols = _nonzero_coords(matrix)
    transposed = auto_transpose and rows.size > 0 and bool(np.all(rows < cols))
    if transposed:  # upper triangular: stored as (earlier, query)
        rows, cols = cols, rows
    return GroundTruth(
        shape[0], rows, cols, source=source, variable=variable, transposed=transposed
    )


def _refuse_non_finite(array: Any, source: str) -> None:
    """GroundTruthError for a NaN or infinite cell: NaN is non-zero, so it would be a loop."""
    if array.dtype.kind != "f" or array.size == 0:
        return
    flat = np.ravel(array, order="K")  # a view, not a copy, for contiguous arrays
    step = max(1, _BLOCK_BYTES // flat.itemsize)
    bad = sum(
        int(np.count_nonzero(~np.isfinite(flat[i : i + step]))) for i in range(0, flat.size, step)
    )
    if bad:
        raise GroundTruthError(
            f"{source}: {bad} of {flat.size} ground-truth cells are NaN or infinite "
            "(a ground truth holds 1 for a loop, 0 elsewhere)"
        )


def _nonzero_coords(array: npt.NDArray[Any]) -> tuple[IntArray, IntArray]:
    """(row, column) of every non-zero cell, scanning in blocks so big arrays are not copied."""
    # Walk the array in its storage order: MATLAB matrices arrive column-major.
    by_columns = array.flags.f_contiguous and not array.flags.c_contiguous
    view = array.T if by_columns else array
    step = max(1, _BLOCK_BYTES // max(1, view.shape[1] * view.itemsize))
    outer: list[IntArray] = [np.empty(0, np.int64)]
    inner: list[IntArray] = [np.empty(0, np.int64)]
    for start in range(0, view.shape[0], step):
        r, c = np.nonzero(view[start : start + step])
        outer.append(r.astype(np.int64) + start)
        inner.append(c.astype(np.int64))
    rows, cols = np.concatenate(outer), np.concatenate(inner)
    return (cols, rows) if by_columns else (rows, cols)
