#!/usr/bin/env python3
"""Where the Python client's time goes in one warm ``Scene.trace`` (BENCHMARKS §15).

Starts ``rayd serve --threads 2``, makes the diffuse rays of ``bench_vs_open3d.py`` (same
scene, room and seed), and times ``--runs`` warm traces after one untimed one. For each it
prints the wall time, the time until the answer's headers, the time reading its body, the
client process's CPU time (``time.process_time``), the CPU spent encoding RAY1 segments and
reading the answer (both measured by wrapping the package's own functions), and the
server's ``Server-Timing``; then the medians.

    python3 clients/python/bench/client_phases.py ../shared/scenes/dragon-100k.from-ply.glb \\
        [--rayd-bin target/release/rayd] [--runs 11]
"""
import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import urllib3

import rayd
from rayd import formats

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_vs_open3d as b  # noqa: E402  (its rays, room and port helper)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--rayd-bin", type=Path, default=b.REPO / "target" / "release" / "rayd")
    ap.add_argument("--runs", type=int, default=11)
    args = ap.parse_args()
    port = b.free_port()
    data = tempfile.TemporaryDirectory(prefix="rayd-phases-")
    server = subprocess.Popen(
        [str(args.rayd_bin), "serve", "--addr", f"127.0.0.1:{port}", "--data-dir", data.name,
         "--threads", "2", "--max-client-requests", "0"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env={**os.environ, "RAYD_LOG": "warn"})
    try:
        client = rayd.Client(f"http://127.0.0.1:{port}", timeout=600)
        client.wait_ready(60)
        tris = np.asarray(client.upload(args.scene).triangles(), np.float32)
        lo, hi = tris.reshape(-1, 3).min(0), tris.reshape(-1, 3).max(0)
        all_tris = np.concatenate([tris, b.room_around(lo, hi)])
        scene = client.upload(bytes(formats.encode_triangles(all_tris)))
        o, d = b.camera_rays(lo.astype(np.float64), hi.astype(np.float64), 1024, 768)
        primary = scene.trace(o, d, accel="mbvh8")
        normals = rayd.face_normals(all_tris, primary["prim"])
        normals[np.einsum("ij,ij->i", normals, d) > 0] *= -1
        spawned = rayd.spawn_rays(primary, b.diffuse_directions(normals, np.random.default_rng(1)),
                                  all_tris)
        o, d = spawned["origins"], spawned["directions"]

        clock = {"headers": 0.0, "binary": 0.0, "encode": 0.0, "read": 0.0}
        request, binary = client._request, client._binary

        def timed_request(*a, **k):
            t = time.perf_counter()
            r = request(*a, **k)
            clock["headers"] = time.perf_counter() - t
            return r

        def timed_binary(*a, **k):
            t = time.perf_counter()
            r = binary(*a, **k)
            clock["binary"] = time.perf_counter() - t
            return r

        segments = formats.RaySegments.__iter__

        def timed_segments(self):
            g = segments(self)
            while True:
                c = time.process_time()
                x = next(g, None)
                clock["encode"] += time.process_time() - c
                if x is None:
                    return
                yield x

        read = urllib3.response.HTTPResponse.read

        def timed_read(self, *a, **k):
            c = time.process_time()
            try:
                return read(self, *a, **k)
            finally:
                clock["read"] += time.process_time() - c

        client._request, client._binary = timed_request, timed_binary
        formats.RaySegments.__iter__ = timed_segments
        urllib3.response.HTTPResponse.read = timed_read
        rows = []
        for k in range(args.runs + 1):
            clock["encode"] = clock["read"] = 0.0
            t0, c0 = time.perf_counter(), time.process_time()
            hits = scene.trace(o, d, accel="mbvh8", precision="watertight")
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            row = [wall, clock["headers"], clock["binary"] - clock["headers"], cpu,
                   clock["encode"], clock["read"], hits.server_timing.get("trace", float("nan")) / 1e3]
            if k:  # the first is untimed
                rows.append(row)
                print("wall %.1f, headers %.1f, body %.1f, client CPU %.1f (encode %.1f, read %.1f), "
                      "server trace %.1f ms" % tuple(x * 1e3 for x in row))
        med = [statistics.median(c) * 1e3 for c in zip(*rows)]
        print("median: wall %.1f, headers %.1f, body %.1f, client CPU %.1f (encode %.1f, read %.1f), "
              "server trace %.1f ms" % tuple(med))
    finally:
        server.send_signal(signal.SIGTERM)
        server.wait()


if __name__ == "__main__":
    main()
