#!/usr/bin/env python3
"""Times synchronous traces whose bodies arrive slowly, as over a real network, with the
server's accelerator `dacrt`, `mbvh8` and `auto` in turn (BENCHMARKS.md §12.12).

Starts `rayd serve` (2 threads) on a free loopback port with a temporary data directory,
uploads SCENE, then sends RAYS (a RAY1 file) as the body of `POST /v1/scenes/{id}/trace`
at RATE bytes per second (128 KiB pieces, paced), each request a new animation time
(`version=1&time=…`, new geometry every frame). Prints the median time from the request's
first byte to the answer's last, per accelerator, and what `auto` ran. The server and the
client are `http_trace_cpu.py`'s.

    scripts/slow_upload.py ../shared/scenes/CesiumMan.glb /tmp/rays/cesium-frame-256k.ray \\
        --rate 80e6 --requests 6
"""

import argparse
import json
import statistics
from pathlib import Path

from http_trace_cpu import request, serve

ROOT = Path(__file__).resolve().parent.parent


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("rays")
    ap.add_argument("--rate", type=float, default=80e6, help="upload bytes per second")
    ap.add_argument("--requests", type=int, default=6)
    ap.add_argument("--bin", default=str(ROOT / "target" / "release" / "rayd"))
    a = ap.parse_args()
    body = Path(a.rays).read_bytes()
    octet = "application/octet-stream"
    with serve(a.bin, 2) as (port, _, _):
        scene, _, _ = request(port, "POST", "/v1/scenes", Path(a.scene).read_bytes(),
                              "model/gltf-binary")
        sid = json.loads(bytes(scene))["id"]
        times = {k: [] for k in ["dacrt", "mbvh8", "auto"]}
        ran = []
        n = 0
        for _ in range(a.requests):
            for accel in times:
                n += 1
                path = f"/v1/scenes/{sid}/trace?accel={accel}&version=1&time={0.001 * n:.6f}"
                _, headers, phases = request(port, "POST", path, body, octet, rate=a.rate)
                times[accel].append(phases[3])
                if accel == "auto":
                    ran.append(headers["x-rayd-accel"])
    print(f"| {Path(a.scene).name} | {len(body) / 1e6:.1f} MB at {a.rate / 1e6:.0f} MB/s | "
          + " | ".join(f"{statistics.median(v) * 1e3:.1f}" for v in times.values())
          + f" | {', '.join(ran)} |")


if __name__ == "__main__":
    main()
