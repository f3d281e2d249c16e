#!/usr/bin/env python3
"""Time per frame for each detector stage, and peak memory, at growing numbers of frames.

Frames are synthetic: a camera window slides along a textured panorama that wraps around, so
features track (sequences form) and places recur every lap (loop closures). Each size runs in
its own process so that its peak resident memory is its own.

    python -m bench.detector                      # 1k, 10k, 50k frames, uint8 SAD
    python -m bench.detector --frames 1000,10000 --precision uint8,float32
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

import cv2
import numpy as np
import numpy.typing as npt

RATE_HZ = 10.0
FRAME_W, FRAME_H = 160, 120
PANORAMA_W = 4000  # one lap = PANORAMA_W / STEP_PX frames
STEP_PX = 8
STAGES = ("preprocess", "features", "segmentation", "sad", "enhance", "trajectory", "association")


def panorama(seed: int = 7) -> npt.NDArray[np.uint8]:
    """Multi-scale smooth noise plus rectangles: texture with corners, never repeating."""
    rng = np.random.default_rng(seed)
    image: npt.NDArray[np.float32] = np.zeros((FRAME_H, PANORAMA_W), np.float32)
    for scale in (4, 16, 64):
        noise = rng.normal(size=(FRAME_H // scale + 2, PANORAMA_W // scale + 2)).astype(np.float32)
        image += cv2.resize(noise, (PANORAMA_W, FRAME_H), interpolation=cv2.INTER_CUBIC) * scale
    for _ in range(PANORAMA_W):
        x, y = int(rng.integers(0, PANORAMA_W - 20)), int(rng.integers(0, FRAME_H - 20))
        w, h = (int(v) for v in rng.integers(4, 20, 2))
        image[y : y + h, x : x + w] += float(rng.normal(0, 60))
    image -= image.min()
    scaled: npt.NDArray[np.float32] = image * (255.0 / image.max())
    return scaled.astype(np.uint8)


def frame_at(
    pano: npt.NDArray[np.uint8], index: int, rng: np.random.Generator
) -> npt.NDArray[np.uint8]:
    x = (index * STEP_PX) % (PANORAMA_W - FRAME_W)
    noise = rng.integers(-6, 7, (FRAME_H, FRAME_W))
    frame: npt.NDArray[np.int64] = pano[:, x : x + FRAME_W].astype(np.int16) + noise
    return np.clip(frame, 0, 255).astype(np.uint8)


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def run_one(frames: int, precision: str) -> dict[str, object]:
    from doseqslam_logs.detector import DOSeqSLAM, Parameters

    pano = panorama()
    rng = np.random.default_rng(1)
    params = Parameters(difference_precision=precision)  # type: ignore[arg-type]
    detector = DOSeqSLAM(params)
    baseline = rss_mb()
    decisions = 0
    loops = 0
    start = time.perf_counter()
    for i in range(frames):
        for d in detector.push(round(i * 1e9 / RATE_HZ), frame_at(pano, i, rng)):
            decisions += 1
            loops += len(d.loop_closures)
    for d in detector.finish():
        decisions += 1
        loops += len(d.loop_closures)
    wall = time.perf_counter() - start
    return {
        "frames": frames,
        "precision": precision,
        "wall_s": wall,
        "stage_s": detector.timings.seconds,
        "sequences": decisions,
        "loop_closures": loops,
        "store_mb": detector.memory_bytes / 2**20,
        "peak_rss_mb": rss_mb(),
        "baseline_rss_mb": baseline,
    }


def table(results: list[dict[str, object]]) -> str:
    head = ["frames", "SAD", "total ms/frame"] + [f"{s} ms/frame" for s in STAGES]
    head += ["sequences", "loops", "vectors MB", "peak RSS MB", "RSS growth MB", "wall s"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in results:
        n = int(r["frames"])  # type: ignore[call-overload]
        stage = r["stage_s"]
        assert isinstance(stage, dict)
        cells = [f"{n:,}", str(r["precision"]), f"{float(r['wall_s']) / n * 1e3:.2f}"]  # type: ignore[arg-type]
        cells += [f"{stage.get(s, 0.0) / n * 1e3:.3f}" for s in STAGES]
        growth = float(r["peak_rss_mb"]) - float(r["baseline_rss_mb"])  # type: ignore[arg-type]
        cells += [str(r["sequences"]), str(r["loop_closures"]), f"{float(r['store_mb']):.1f}"]  # type: ignore[arg-type]
        cells += [f"{float(r['peak_rss_mb']):.0f}", f"{growth:.0f}", f"{float(r['wall_s']):.1f}"]  # type: ignore[arg-type]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--frames", default="1000,10000,50000", help="comma-separated sizes")
    parser.add_argument("--precision", default="uint8", help="uint8, float32 or both (comma)")
    parser.add_argument(
        "--max-float32-frames",
        type=int,
        default=10000,
        help="skip float32 above this size (it is ~18x slower in the SAD)",
    )
    parser.add_argument("--run", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--json", action="store_true", help="print raw results as JSON")
    args = parser.parse_args()
    if args.run:
        print(json.dumps(run_one(args.run, args.precision)))
        return 0
    results = []
    for precision in args.precision.split(","):
        for n in (int(v) for v in args.frames.split(",")):
            if precision == "float32" and n > args.max_float32_frames:
                continue
            print(f"running {n} frames, {precision} SAD ...", file=sys.stderr, flush=True)
            out = subprocess.run(
                [sys.executable, __file__, "--run", str(n), "--precision", precision],
                check=True,
                capture_output=True,
                text=True,
            ).stdout
            results.append(json.loads(out))
    print(json.dumps(results, indent=1) if args.json else table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
