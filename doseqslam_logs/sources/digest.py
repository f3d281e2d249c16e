"""The sha256 a run records of its input, and the check that a log given later (a sidecar's
`--source`, `--poses-from`) is that input. Light on purpose: `evaluate`, `export` and
`optimize` check before they load anything heavy.
"""

from __future__ import annotations

import errno
import hashlib
from pathlib import Path

HASH_BLOCK = 1 << 20


def source_sha256(path: Path) -> str:
    """sha256 of a log file; of a rosbag2 folder, of its files' names and bytes in name order."""
    if not (path.is_file() or path.is_dir()) and path.exists():
        # A pipe or device: reading it would block or consume it; the run's reader refuses it.
        raise OSError(errno.ESPIPE, "not a regular file", str(path))
    digest = hashlib.sha256()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for file in files:
        if path.is_dir():
            digest.update(file.relative_to(path).as_posix().encode() + b"\0")
        with file.open("rb") as stream:
            while block := stream.read(HASH_BLOCK):
                digest.update(block)
    return digest.hexdigest()
