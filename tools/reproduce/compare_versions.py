"""Annotate the same logs with this version and an earlier one, on this machine, and compare.

    python -m reproduce.compare_versions 4c02724                     # the committed samples
    python -m reproduce.compare_versions 4c02724 LOG... -- --no-verify

The earlier version is taken from git (`git archive REV`) into a temporary folder and run from
there; this version is the installed package. Both run here, one after the other, so the bytes
can be compared: the outputs depend on floating-point kernels, and so only on one machine are
they expected to be the same (see sample_logs/README.md). Prints one line per log and exits 1
when any output differs.

With `cache` (the tests pass DOSEQSLAM_REFERENCE_CACHE, default ~/.cache/doseqslam-reference),
the earlier version's outputs are kept between runs, keyed by what their bytes depend on: the
commit, the log's bytes, the options, and this machine and its libraries (`environment`). A
new processor, library version or Python makes new keys, never a stale match.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import hashlib
import importlib.metadata
import io
import os
import platform
import shutil
import subprocess
import sys
import tarfile
import tempfile
from collections.abc import Callable
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SAMPLES = [
    "drive_loops.ros2.mcap",
    "drive_loops.foxglove.mcap",
    "drive_loops.bag",
    "drive_loops.rosbag2",
    "drive_varrate.bag",
    "drive_parked.ros2.mcap",
]


def extract(revision: str, folder: Path) -> Path:
    """The package of `revision`, importable from the returned folder."""
    archive = subprocess.run(
        ["git", "-C", str(REPO), "archive", revision, "doseqslam_logs", "schemas"],
        check=True,
        capture_output=True,
    ).stdout
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(folder, filter="data")
    return folder


def annotate(python_path: Path | None, log: Path, output: Path, extra: list[str]) -> None:
    """One `doseqslam-logs annotate` run in a fresh process (the installed version when
    `python_path` is None)."""
    env = dict(os.environ)
    if python_path is not None:
        env["PYTHONPATH"] = str(python_path)
    command = [sys.executable, "-m", "doseqslam_logs.cli.main", "annotate", str(log)]
    subprocess.run(
        [*command, "-o", str(output), *extra],
        check=True,
        capture_output=True,
        env=env,
        cwd=output.parent,
    )


# The distributions whose code computes or writes the outputs' bytes.
DISTRIBUTIONS = (
    "numpy",
    "opencv-contrib-python-headless",
    "faiss-cpu",
    "scipy",
    "rosbags",
    "mcap",
    "mcap-ros2-support",
    "zstandard",
    "lz4",
)


@functools.cache
def environment() -> str:
    """What an output's bytes depend on besides the code and the log: Python, the libraries'
    versions, the processor (its model and instruction sets: floating-point kernels differ).
    Read once a process: it does not change under a run."""
    versions = []
    for name in DISTRIBUTIONS:
        try:
            versions.append(f"{name}=={importlib.metadata.version(name)}")
        except importlib.metadata.PackageNotFoundError:
            versions.append(f"{name} absent")
    cpu = ""
    with contextlib.suppress(OSError):
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        cpu = "\n".join(sorted({ln for ln in lines if ln.startswith(("model name", "flags"))}))
    return "\n".join([sys.version, platform.machine(), cpu, *versions])


def cache_key(revision: str, log: Path, extra: list[str]) -> str:
    """The key of `revision`'s output for `log` annotated with `extra` on this machine."""
    commit = subprocess.run(
        ["git", "-C", str(REPO), "rev-parse", f"{revision}^{{commit}}"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    digest = hashlib.sha256()
    for part in (commit, repr(extra), environment()):
        digest.update(part.encode() + b"\0")
    files = sorted(f for f in log.rglob("*") if f.is_file()) if log.is_dir() else [log]
    for file in files:  # a bag folder: its files in order
        digest.update(file.relative_to(log.parent).as_posix().encode() + b"\0")
        digest.update(file.read_bytes())
    return digest.hexdigest()[:32]


def same_bytes(old: Path, new: Path) -> bool:
    return old.read_bytes() == new.read_bytes()


def same_decisions(old: Path, new: Path) -> bool:
    """The same loop-closure and sequence records, read back by this version's reader (which
    reads every older output): the detector's and verification's decisions, whatever else the
    files hold (metadata entries, visualization channels, schema text). Compared by repr, so
    that NaN fields compare equal."""
    from doseqslam_logs.annotations.reader import read_annotations

    before, after = read_annotations(old), read_annotations(new)
    return (repr(before.loop_closures), repr(before.sequences)) == (
        repr(after.loop_closures),
        repr(after.sequences),
    )


def compare(
    revision: str,
    logs: list[Path],
    extra: list[str],
    work: Path,
    same: Callable[[Path, Path], bool] = same_bytes,
    current: Callable[[Path], Path] | None = None,
    cache: Path | None = None,
) -> list[tuple[str, bool]]:
    """(log name, `same(output of revision, output of this version)`) for each log;
    `current(log)`: this version's output when it was made already (a test's shared one);
    `cache`: a folder keeping the revision's outputs between runs (module docstring)."""
    before = extract(revision, work / revision)
    results = []
    for log in logs:
        old, new = work / f"{log.name}.{revision}.mcap", work / f"{log.name}.after.mcap"
        _earlier_output(before, log, old, extra, revision, cache)
        if current is not None:
            new = current(log)
        elif not new.exists():  # this version's output, shared by comparisons in one `work`
            annotate(None, log, new, extra)
        results.append((log.name, same(old, new)))
    return results


def _earlier_output(
    before: Path, log: Path, output: Path, extra: list[str], revision: str, cache: Path | None
) -> None:
    """`output`: the earlier version's annotation of `log`, from `cache` when it is there."""
    kept = None if cache is None else cache / f"{cache_key(revision, log, extra)}.mcap"
    if kept is not None and kept.is_file():
        shutil.copyfile(kept, output)
        return
    annotate(before, log, output, extra)
    if kept is not None:  # written beside, then renamed: a concurrent run never reads half
        kept.parent.mkdir(parents=True, exist_ok=True)
        partial = kept.with_name(f".{kept.name}.{os.getpid()}")
        shutil.copyfile(output, partial)
        partial.replace(kept)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("revision", help="the earlier version: a commit, tag or branch")
    parser.add_argument("logs", nargs="*", type=Path, help="default: the committed samples")
    parser.epilog = "Options after -- go to both annotate runs."
    args = parser.parse_args(argv[: len(argv) - len(extra) - ("--" in argv)])
    logs = args.logs or [REPO / "sample_logs" / name for name in SAMPLES]
    with tempfile.TemporaryDirectory() as tmp:
        results = compare(args.revision, [log.resolve() for log in logs], extra, Path(tmp))
    for name, same in results:
        print(f"{name}: {'same bytes' if same else 'DIFFERENT'}")
    return 0 if all(same for _, same in results) else 1


if __name__ == "__main__":
    sys.exit(main())
