"""Run a command as if on an older processor: NumPy's and OpenCV's SIMD dispatch switched off.

    python -m loggen.other_processor -- .venv/bin/pytest tests
    python -m loggen.other_processor --print   # its environment, as shell lines

NumPy and OpenCV pick kernels at run time by what the processor offers (AVX2, AVX-512, NEON
extensions). Their float kernels round differently in the last bit, so a result that holds only
on the machine that wrote it shows up here: everything above each library's compiled-in baseline
is disabled through their own switches, `NPY_DISABLE_CPU_FEATURES` and `OPENCV_CPU_DISABLE`.
On x86-64 that is SSE3 (OpenCV) and x86-64-v2 (NumPy) instead of AVX-512; on arm64, plain NEON.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys


def numpy_dispatched() -> list[str]:
    """NumPy's run-time dispatched SIMD targets this processor has (empty if it cannot tell)."""
    import importlib

    for name in ("numpy._core._multiarray_umath", "numpy.core._multiarray_umath"):  # 2.x, 1.x
        try:
            umath = importlib.import_module(name)
            break
        except ImportError:
            continue
    else:
        return []
    features = getattr(umath, "__cpu_features__", {})
    return [name for name in getattr(umath, "__cpu_dispatch__", []) if features.get(name)]


def opencv_dispatched() -> list[str]:
    """OpenCV's dispatched optimizations this processor has: the starred, unquestioned names of
    `cv2.getCPUFeaturesLine()` ("SSE SSE2 SSE3 *SSE4.1 ... *AVX512-SKX")."""
    import cv2

    words = cv2.getCPUFeaturesLine().split()
    return [w[1:] for w in words if w.startswith("*") and not w.endswith("?")]


def baseline_environment() -> dict[str, str]:
    """The variables that switch both libraries to their baseline kernels ({} if none apply)."""
    env = {}
    if numpy_names := numpy_dispatched():
        env["NPY_DISABLE_CPU_FEATURES"] = " ".join(numpy_names)
    if opencv_names := opencv_dispatched():
        env["OPENCV_CPU_DISABLE"] = ",".join(opencv_names)
    return env


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--print", action="store_true", help="print the variables and exit")
    parser.add_argument("command", nargs="*", help="the command to run (after --)")
    args = parser.parse_args(argv)
    env = baseline_environment()
    if args.print or not args.command:
        for name, value in env.items():
            print(f"export {name}='{value}'")
        return 0
    if not env:
        print("other_processor: no dispatched SIMD to switch off here", file=sys.stderr)
    return subprocess.call(args.command, env={**os.environ, **env})


if __name__ == "__main__":
    sys.exit(main())
