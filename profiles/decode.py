"""Frame decoding throughput: read + decode + photometric correction + undistortion, per frame and iterated.

Prints one JSON line. For each dataset (default: the KITTI 00 excerpt, 1241x376 PNG, no distortion, and the EuRoC
V1_01 excerpt, 752x480 PNG with radial-tangential distortion, remapped), medians over ``--repeats`` passes of:

- ``decode_ms``: file read + PNG/JPEG decode (``Sequence.load_raw``);
- ``load_ms``: the whole ``Sequence.load`` (decode, gray conversion, photometric correction, undistortion);
- ``undistort_ms``: ``Calibration.gray_from_raw`` alone (0-ish for KITTI: passthrough);
- ``rgb_ms``: the lazy ``Frame.rgb`` (undistorted RGB float), paid for keyframes only;
- ``fps_iter``: frames/s of ``for f in seq.frames(prefetch=0)`` and ``prefetch=N``, bare;
- ``fps_with_consumer``: the same while the consumer spends ``--consumer-ms`` per frame with the GIL released (a
  stand-in for the tracker): prefetch overlaps decoding with it.

Usage: ``python profiles/decode.py [--path P ...] [--frames N] [--prefetch N] [--repeats R] [--consumer-ms MS]``
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import cv2

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mgso.config import InputConfig  # noqa: E402
from mgso.io import open_sequence, shared_data_dir  # noqa: E402


def per_frame_ms(fn, n: int, repeats: int) -> float:
    """Median over repeats of the mean time of ``fn(i)`` over ``n`` frames, in ms."""
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for i in range(n):
            fn(i)
        runs.append((time.perf_counter() - t0) * 1e3 / n)
    return statistics.median(runs)


def iter_fps(seq, prefetch: int, repeats: int, consumer_s: float) -> float:
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        n = 0
        for _f in seq.frames(prefetch=prefetch):
            if consumer_s:
                time.sleep(consumer_s)
            n += 1
        runs.append(n / (time.perf_counter() - t0))
    return statistics.median(runs)


def profile(path: Path, frames: int, prefetch: int, repeats: int, consumer_ms: float) -> dict:
    seq = open_sequence(path, config=InputConfig(end=frames))
    n = len(seq)
    seq.load(0)  # warm the file cache, as a second pass over a recording would
    raws = [seq.load_raw(i) for i in range(n)]
    gray_raws = [r if r.ndim == 2 else cv2.cvtColor(r, cv2.COLOR_BGR2GRAY) for r in raws]
    cal = seq.calibration
    out = {
        "layout": seq.layout, "frames": n, "size_in": list(cal.input_size), "size_out": list(cal.output_size),
        "undistortion": cal.undistorter.kind, "photometric": not cal.photometric.is_identity,
        "decode_ms": round(per_frame_ms(seq.load_raw, n, repeats), 3),
        "undistort_ms": round(per_frame_ms(lambda i: cal.gray_from_raw(gray_raws[i]), n, repeats), 3),
        "load_ms": round(per_frame_ms(seq.load, n, repeats), 3),
        "rgb_ms": round(per_frame_ms(lambda i: cal.rgb_from_raw(raws[i]), n, repeats), 3),
    }
    out["load_fps"] = round(1e3 / out["load_ms"], 1)
    out["fps_iter"] = {"prefetch=0": round(iter_fps(seq, 0, repeats, 0.0), 1)}
    out["fps_with_consumer"] = {"consumer_ms": consumer_ms,
                                "prefetch=0": round(iter_fps(seq, 0, repeats, consumer_ms / 1e3), 1)}
    if prefetch > 0:
        out["fps_iter"][f"prefetch={prefetch}"] = round(iter_fps(seq, prefetch, repeats, 0.0), 1)
        out["fps_with_consumer"][f"prefetch={prefetch}"] = round(iter_fps(seq, prefetch, repeats,
                                                                          consumer_ms / 1e3), 1)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--path", action="append", help="dataset folder or video (repeatable); default: the KITTI and "
                                                    "EuRoC excerpts of the shared data")
    ap.add_argument("--frames", type=int, default=60, help="frames per pass (from the start)")
    ap.add_argument("--prefetch", type=int, default=2, help="prefetch depth to compare with none (0: skip)")
    ap.add_argument("--repeats", type=int, default=3, help="passes; medians are reported")
    ap.add_argument("--consumer-ms", type=float, default=15.0, help="per-frame work of the simulated consumer")
    args = ap.parse_args(argv)
    if args.path:
        paths = {Path(p).name: Path(p) for p in args.path}
    else:
        data = shared_data_dir()
        if data is None:
            print(json.dumps({"error": "shared data not found: set MGSO_DATA or pass --path"}))
            return 2
        paths = {"kitti00_0-159": data / "kitti00_0-159", "euroc_v101_first95": data / "euroc_v101_first95"}
    result = {"profile": "decode", "repeats": args.repeats, "cpu_count": os.cpu_count(),
              "opencv_threads": cv2.getNumThreads()}
    for name, p in paths.items():
        result[name] = profile(p, args.frames, args.prefetch, args.repeats, args.consumer_ms)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
