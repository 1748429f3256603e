#!/usr/bin/env python3
"""Times small synchronous traces sent while a large synchronous DACRT trace runs
(BENCHMARKS.md §40).

Starts `rayd serve` (2 threads) on a free loopback port with a temporary data directory,
uploads SCENE, then sends a batch of BIG rays (`accel=dacrt-sampled`) and, from the moment
its body is in, a 1K-ray trace (`accel=mbvh8`) every 50 ms until the big one answers. Prints
the big trace's time (first byte to last), how many small traces ran meanwhile, and their
median and longest times: how long work that arrives behind a DACRT batch waits for it. Rays go from random points of a box twice the scene's
size towards random points of its bounds.

    scripts/trace_behind_dacrt.py ../shared/scenes/DamagedHelmet.glb --big 4194304
"""

import argparse
import json
import random
import statistics
import struct
import multiprocessing
import time
from pathlib import Path

from http_trace_cpu import request, serve

ROOT = Path(__file__).resolve().parent.parent


def rays(n, lo, hi, seed):
    rng = random.Random(seed)
    c = [(a + b) / 2 for a, b in zip(lo, hi)]
    ext = [max(b - a, 1e-3) for a, b in zip(lo, hi)]
    out = bytearray(struct.pack("<IHHQ", 0x31594152, 1, 0, n))
    rec = struct.Struct("<8f")
    for _ in range(n):
        o = [c[k] + ext[k] * (rng.random() * 2 - 1) for k in range(3)]
        t = [lo[k] + ext[k] * rng.random() for k in range(3)]
        out += rec.pack(*o, 0.0, *(t[k] - o[k] for k in range(3)), float("inf"))
    return bytes(out)


def run_big(port, sid, big, done):
    _, _, phases = request(port, "POST", f"/v1/scenes/{sid}/trace?accel=dacrt-sampled", big,
                           "application/octet-stream")
    done.put(phases[3])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--big", type=int, default=1 << 22, help="rays of the DACRT batch")
    ap.add_argument("--bin", default=str(ROOT / "target" / "release" / "rayd"))
    ap.add_argument("--verbose", action="store_true", help="print every small trace's time")
    ap.add_argument("--alone", action="store_true",
                    help="no small traces: time the big one by itself")
    a = ap.parse_args()
    if a.big <= 0 or a.big % (1 << 16):
        ap.error("--big must be a positive multiple of 65536 (the batch repeats 64K rays)")
    octet = "application/octet-stream"
    with serve(a.bin, 2) as (port, _, _):
        body, _, _ = request(port, "POST", "/v1/scenes", Path(a.scene).read_bytes(),
                             "model/gltf-binary")
        info = json.loads(bytes(body))
        sid = info["id"]
        lo, hi = info["bounds"]["min"], info["bounds"]["max"]
        small = rays(1024, lo, hi, 2)
        # The big batch is the small one repeated: making millions of random rays in
        # Python would take longer than the trace.
        unit = rays(1 << 16, lo, hi, 1)[16:]
        big = struct.pack("<IHHQ", 0x31594152, 1, 0, a.big) + unit * (a.big >> 16)
        # Warm the structures (the BVH of the small traces, DACRT's precompute).
        request(port, "POST", f"/v1/scenes/{sid}/trace?accel=mbvh8", small, octet)
        request(port, "POST", f"/v1/scenes/{sid}/trace?accel=dacrt-sampled", small, octet)
        # The big trace goes from another process: a thread would hold the GIL while it
        # reads its 100+ MB answer, and the small traces' times would count the wait.
        done = multiprocessing.Queue()
        t = multiprocessing.Process(target=run_big, args=(port, sid, big, done))
        t.start()
        # The body of 128 MiB takes a while on loopback: start once the server has it.
        time.sleep(len(big) / 1.5e9 + 0.05)
        waits, timings = [], []
        while t.is_alive() and not a.alone:
            t0 = time.perf_counter()
            _, headers, _ = request(port, "POST", f"/v1/scenes/{sid}/trace?accel=mbvh8", small,
                                    octet)
            waits.append(time.perf_counter() - t0)
            timings.append(headers.get("server-timing", ""))
            time.sleep(0.05)
        big_s = done.get()
        t.join()
    if a.verbose:
        for w, st in zip(waits, timings):
            print(f"{w * 1e3:.0f} ms; Server-Timing: {st}")
    if a.alone:
        print(f"| {Path(a.scene).name} | {a.big} | {big_s:.3f} | alone |")
        return
    print(f"| {Path(a.scene).name} | {a.big} | {big_s:.3f} | {len(waits)} | "
          f"{statistics.median(waits) * 1e3:.0f} | {max(waits) * 1e3:.0f} |")


if __name__ == "__main__":
    main()
