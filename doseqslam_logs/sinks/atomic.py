"""Write a file so that it appears whole under its final name, or not at all.

The data goes to a hidden temporary file beside the final name, `.NAME.PID.RANDOM.tmp`, that is
renamed over NAME when complete and removed on any error, KeyboardInterrupt or SIGTERM (the
command line turns SIGTERM into KeyboardInterrupt). Only a process killed outright (SIGKILL,
power loss) leaves its temporary file behind; the next write of the same NAME on the same
machine removes such files when the process that made them no longer runs. A NAME too long to
leave room for that decoration is shortened in the temporary name, `.PREFIX~HASH.PID.RANDOM.tmp`,
so that every name the file system allows can be written.

Only regular files are ever replaced: an existing FIFO, device, socket or directory under the
final name is refused (OutputError) and left alone. A symbolic link is judged by what it points
to; when that is a regular file (or nothing), the rename replaces the link itself with the new
file and the link's target is never written.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
import secrets
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

from ..errors import DoseqslamError, OutputError

TEMP_SUFFIX = ".tmp"
NAME_MAX = 255  # bytes of one file name on Linux, macOS and Windows file systems
# What temp_name adds around the stem: the dot before it, ".PID" (up to 10 digits), ".RANDOM".
_TEMP_DECORATION = 1 + 11 + 9 + len(TEMP_SUFFIX)
_KINDS = {
    stat.S_IFIFO: "a FIFO",
    stat.S_IFCHR: "a character device",
    stat.S_IFBLK: "a block device",
    stat.S_IFSOCK: "a socket",
    stat.S_IFDIR: "a directory",
}


def _temp_stem(final: Path) -> str:
    """`final`'s name, or, when the decoration would make it longer than NAME_MAX, its head
    and a hash of the whole name: the same stem for the same name in every process."""
    name = os.fsencode(final.name)
    if len(name) + _TEMP_DECORATION <= NAME_MAX:
        return final.name
    digest = hashlib.sha256(name).hexdigest()[:8]
    head = name[: NAME_MAX - _TEMP_DECORATION - len(digest) - 1]
    return f"{os.fsdecode(head)}~{digest}"


def temp_name(final: Path) -> Path:
    """A fresh hidden name beside `final`, so that os.replace stays on one file system."""
    stem = _temp_stem(final)
    return final.with_name(f".{stem}.{os.getpid()}.{secrets.token_hex(4)}{TEMP_SUFFIX}")


def check_output_path(final_path: str | os.PathLike[str]) -> None:
    """Raises OutputError unless `final_path` may become a regular file of ours: absent, or a
    regular file (a symlink is followed, see the module's docstring), with a name that fits."""
    final = Path(final_path)
    length = len(os.fsencode(final.name))
    if length > NAME_MAX:
        raise OutputError(
            f"{final}: cannot create the output: its name is {length} bytes long, "
            f"the limit is {NAME_MAX}"
        )
    try:
        mode = os.stat(final).st_mode
    except FileNotFoundError:
        return
    except OSError as exc:
        raise OutputError(f"{final}: cannot create the output: {exc.strerror or exc}") from exc
    if not stat.S_ISREG(mode):
        kind = _KINDS.get(stat.S_IFMT(mode), "not a regular file")
        raise OutputError(f"{final}: the output exists and is {kind}: refusing to replace it")


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
        rf"\.{re.escape(_temp_stem(final))}\.(\d+)\.[0-9a-f]{{8}}{re.escape(TEMP_SUFFIX)}"
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


def _create_temp(final: Path, created: list[Path]) -> BinaryIO:
    """A new temporary file beside `final`, its path appended to `created` before it exists:
    a KeyboardInterrupt (Ctrl-C, SIGTERM) can land between any two lines, and whoever cleans
    up must know the name of a file that open() has just made."""
    for _ in range(100):
        path = temp_name(final)
        created.append(path)
        try:
            # O_EXCL: never write into someone else's file; mode 0o666 lets the umask decide,
            # as it would for a plain open().
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:
            created.remove(path)  # not ours: never removed
            continue
        return os.fdopen(fd, "wb")
    raise FileExistsError(f"no free temporary name beside {final}")


def _remove(paths: list[Path]) -> None:
    for path in paths:
        with contextlib.suppress(OSError):
            path.unlink()


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

    On success the data is flushed and fsynced, then renamed over `final_path`, replacing an
    existing regular file atomically (anything else there is refused, before and after
    writing: OutputError). On any exception the temporary file is removed and nothing appears
    under `final_path`; `DoseqslamError`s and BaseExceptions (KeyboardInterrupt) pass through
    unchanged, other exceptions are raised as OutputError naming the file.
    """
    final = Path(final_path)
    check_output_path(final)
    remove_stale_temps(final)
    created: list[Path] = []
    try:
        try:
            stream = _create_temp(final, created)
        except OSError as exc:
            raise OutputError(f"{final}: cannot create the output: {exc.strerror or exc}") from exc
        with stream:
            yield stream
            stream.flush()
            os.fsync(stream.fileno())
        check_output_path(final)  # again: it may have appeared while we wrote
        os.replace(created[-1], final)
    except BaseException as exc:
        _remove(created)
        if isinstance(exc, DoseqslamError) or not isinstance(exc, Exception):
            raise
        raise OutputError(f"{final}: cannot write the output: {exc}") from exc
    _fsync_directory(final.parent)


@contextlib.contextmanager
def atomic_path(final_path: str | os.PathLike[str]) -> Iterator[Path]:
    """`atomic_output` for a writer that creates its file itself (rosbags' bag writer refuses
    an existing one): a fresh temporary name beside `final_path`, not yet created, that becomes
    `final_path` when the block succeeds (fsynced, then renamed), and is removed on any
    exception. The same checks and error rules as `atomic_output`."""
    final = Path(final_path)
    check_output_path(final)
    remove_stale_temps(final)
    temporary = temp_name(final)
    try:
        yield temporary
        with temporary.open("rb") as written:
            os.fsync(written.fileno())
        check_output_path(final)  # again: it may have appeared while we wrote
        os.replace(temporary, final)
    except BaseException as exc:
        _remove([temporary])
        if isinstance(exc, DoseqslamError) or not isinstance(exc, Exception):
            raise
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        raise OutputError(f"{final}: cannot write the output: {why}") from exc
    _fsync_directory(final.parent)


@contextlib.contextmanager
def scratch_file(final_path: str | os.PathLike[str]) -> Iterator[Path]:
    """An empty hidden file beside `final_path`, named like its temporary files (so that a
    later run removes it if this process is killed), removed when the block ends."""
    final = Path(final_path)
    check_output_path(final)
    created: list[Path] = []
    try:
        try:
            _create_temp(final, created).close()
        except OSError as exc:
            raise OutputError(
                f"{final}: cannot create a temporary file: {exc.strerror or exc}"
            ) from exc
        yield created[-1]
    finally:
        _remove(created)
