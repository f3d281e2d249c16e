"""Write a file so that it appears whole under its final name, or not at all.

The data goes to a hidden temporary file beside the final name, `.NAME.PID.RANDOM.tmp`, that is
renamed over NAME when complete and removed on any error, KeyboardInterrupt or SIGTERM (the
command line turns SIGTERM into KeyboardInterrupt). Only a process killed outright (SIGKILL,
power loss) leaves its temporary file behind; the next write of the same NAME on the same
machine removes such files when the process that made them no longer runs.
"""

from __future__ import annotations

import contextlib
import os
import re
import secrets
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

from ..errors import DoseqslamError, OutputError

TEMP_SUFFIX = ".tmp"


def temp_name(final: Path) -> Path:
    """A fresh hidden name beside `final`, so that os.replace stays on one file system."""
    return final.with_name(f".{final.name}.{os.getpid()}.{secrets.token_hex(4)}{TEMP_SUFFIX}")


def _pid_is_running(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):
        return False
    except PermissionError:
        return True  # it runs, as another user
    return True


def remove_stale_temps(final: Path) -> list[Path]:
    """Remove the temporary files of `final` left by processes that no longer run (killed
    mid-write); returns them. Temporaries of running processes are left alone."""
    pattern = re.compile(
        rf"\.{re.escape(final.name)}\.(\d+)\.[0-9a-f]{{8}}{re.escape(TEMP_SUFFIX)}"
    )
    removed = []
    with contextlib.suppress(OSError):
        for path in final.parent.iterdir():
            match = pattern.fullmatch(path.name)
            if match is None or int(match.group(1)) == os.getpid():
                continue
            if not _pid_is_running(int(match.group(1))):
                with contextlib.suppress(OSError):
                    path.unlink()
                    removed.append(path)
    return removed


def _create_temp(final: Path) -> tuple[Path, BinaryIO]:
    for _ in range(100):
        path = temp_name(final)
        try:
            # O_EXCL: never write into someone else's file; mode 0o666 lets the umask decide,
            # as it would for a plain open().
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:
            continue
        return path, os.fdopen(fd, "wb")
    raise FileExistsError(f"no free temporary name beside {final}")


def _fsync_directory(folder: Path) -> None:
    # Makes the rename itself durable; not every platform can open a directory.
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


@contextlib.contextmanager
def atomic_output(final_path: str | os.PathLike[str]) -> Iterator[BinaryIO]:
    """A binary stream to a temporary file that becomes `final_path` when the block succeeds.

    On success the data is flushed and fsynced, then renamed over `final_path` (replacing an
    existing file atomically). On any exception the temporary file is removed and nothing
    appears under `final_path`; `DoseqslamError`s and BaseExceptions (KeyboardInterrupt) pass
    through unchanged, other exceptions are raised as OutputError naming the file.
    """
    final = Path(final_path)
    remove_stale_temps(final)
    try:
        temp, stream = _create_temp(final)
    except OSError as exc:
        raise OutputError(f"{final}: cannot create the output: {exc.strerror or exc}") from exc
    try:
        with stream:
            yield stream
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temp, final)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            temp.unlink()
        if isinstance(exc, DoseqslamError) or not isinstance(exc, Exception):
            raise
        raise OutputError(f"{final}: cannot write the output: {exc}") from exc
    _fsync_directory(final.parent)


@contextlib.contextmanager
def scratch_file(final_path: str | os.PathLike[str]) -> Iterator[Path]:
    """An empty hidden file beside `final_path`, named like its temporary files (so that a
    later run removes it if this process is killed), removed when the block ends."""
    final = Path(final_path)
    try:
        path, stream = _create_temp(final)
    except OSError as exc:
        raise OutputError(
            f"{final}: cannot create a temporary file: {exc.strerror or exc}"
        ) from exc
    stream.close()
    try:
        yield path
    finally:
        with contextlib.suppress(OSError):
            path.unlink()
