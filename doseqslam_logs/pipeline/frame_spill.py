"""The detector's older frame vectors in an unlinked temporary file (a `ByteSpill`).

A frame vector is 2,048 B and the detector keeps one per frame for SAD windows anywhere in the
past: 295 MB for a 4-hour 10 Hz log. The replay gives its `FrameStore` this spill, so only the
newest blocks stay in memory and the rest are read back with os.pread when a window needs
them (the operating system's page cache usually answers; it is not the process's memory).

The file is created already unlinked (`tempfile.TemporaryFile`, in TMPDIR or the system's
temporary folder): nothing is left behind, even when the process is killed.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ..closing import Closing
from ..detector import Parameters
from ..detector.difference import FrameStore
from ..errors import OutputError


class FileSpill(Closing):
    """Bytes at offsets of an unlinked temporary file. Use as a context manager."""

    def __init__(
        self, directory: str | Path | None = None, what: str = "the frame vectors"
    ) -> None:
        self._what = what  # named in the errors
        try:
            self._file = tempfile.TemporaryFile(dir=directory)  # noqa: SIM115 (closed by close)
        except OSError as exc:
            raise OutputError(
                f"cannot create a temporary file for {what}: {exc.strerror or exc}"
            ) from exc
        self.bytes = 0  # bytes written so far

    def write(self, offset: int, data: memoryview) -> None:
        """Raises OutputError when the disk refuses them (full, read-only)."""
        fd = self._file.fileno()
        done = 0
        try:
            while done < len(data):
                done += os.pwrite(fd, data[done:], offset + done)
        except OSError as exc:
            raise OutputError(
                f"cannot write the temporary file of {self._what}: {exc.strerror or exc}"
            ) from exc
        self.bytes = max(self.bytes, offset + len(data))

    def read_into(self, offset: int, out: memoryview) -> None:
        """Raises OSError when the file holds fewer bytes there than asked."""
        fd = self._file.fileno()
        done = 0
        while done < len(out):
            got = os.preadv(fd, [out[done:]], offset + done)
            if got == 0:
                raise OSError(f"temporary file of {self._what}: {len(out) - done} bytes missing")
            done += got

    def close(self) -> None:
        self._file.close()


@contextmanager
def spilled_frame_store(params: Parameters) -> Iterator[FrameStore]:
    """The detector's frame store for these parameters, its older blocks in a FileSpill that
    is closed (and so gone) when the block ends."""
    with FileSpill() as spill:
        dimension = params.image_width * params.image_height
        yield FrameStore(dimension, params.difference_precision, spill=spill)
