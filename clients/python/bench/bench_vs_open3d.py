#!/usr/bin/env python3
"""The same diffuse rays through the rayd Python client and through Open3D, in one run.

    python3 clients/python/bench/bench_vs_open3d.py ../shared/scenes/dragon-100k.from-ply.glb

What it does, so that both tracers see exactly the same rays and triangles:

1. starts ``rayd serve --threads N`` on a free loopback port (or uses ``--url``), uploads
   the scene and fetches its triangles (``GET /v1/scenes/{id}/geometry``);
2. closes the scene in a room (a cube of 12 triangles around its bounds, as
   ``rayd bench`` does, so that every ray hits) and uploads scene + room as one TRI1 scene;
3. makes ``--width × --height`` camera rays from inside the room, traces them with the
   client and turns each hit into one diffuse ray (a cosine-weighted direction about the
   normal facing the camera, origins offset by ``rayd.spawn_rays``; tmin 0, tmax inf), so
   1024×768 gives 786,432 diffuse rays, every one of which hits;
4. times, after one untimed warm-up each (which builds the acceleration structures):
   ``scene.trace(origins, directions)`` (numpy in, ``t, prim, u, v`` numpy out: encoding,
   HTTP on loopback, the server's trace, decoding), ``scene.cast_rays(rays)`` (the same plus
   Open3D's five arrays with normals), and Open3D's ``RaycastingScene.cast_rays`` on the same
   ``(N, 6)`` float32 array in this process with the same thread count, ``.numpy()`` of every
   result included. Median of ``--runs``;
5. prints Mray/s for each as a Markdown table, the server's own trace time
   (``Server-Timing``), and how often the two tracers agree on the triangle hit.

Needs ``pip install ./clients/python open3d-cpu`` (Open3D needs Debian's ``libusb-1.0-0``)
and a built ``target/release/rayd`` (or ``--rayd-bin``). A benchmark: run it on a quiet
machine, not in CI.
"""

from __future__ import annotations

import argparse
import os
import platform
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

import rayd
from rayd import formats
from timing import median as timed

REPO = Path(__file__).resolve().parents[3]


def room_around(lo, hi):
    """12 triangles of a closed cube around the bounds ``lo..hi``, four times their largest
    half-extent from the centre on every side."""
    c, h = (lo + hi) / 2, np.full(3, 4 * max(float(np.max(hi - lo)) / 2, 1e-3))
    x0, y0, z0 = c - h
    x1, y1, z1 = c + h
    v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], np.float32)
    quads = [(0, 1, 2, 3), (4, 7, 6, 5), (0, 4, 5, 1), (3, 2, 6, 7), (0, 3, 7, 4), (1, 5, 6, 2)]
    tris = []
    for a, b, c_, d in quads:
        tris += [(v[a], v[b], v[c_]), (v[a], v[c_], v[d])]
    return np.array(tris, np.float32)


def camera_rays(lo, hi, width, height, fov_deg=50.0):
    """Pinhole rays from in front of the scene, inside the room, through every pixel."""
    centre, half = (lo + hi) / 2, max(float(np.max(hi - lo)) / 2, 1e-3)
    eye = centre + np.array([0.6, 0.8, 2.5]) * half  # inside the room (4 half-extents)
    forward = centre - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    half = np.tan(np.radians(fov_deg) / 2)
    xs = (np.arange(width) + 0.5) / width * 2 - 1
    ys = 1 - (np.arange(height) + 0.5) / height * 2
    px, py = np.meshgrid(xs * half * width / height, ys * half)
    d = forward + px[..., None] * right + py[..., None] * up
    d = d.reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.broadcast_to(eye, d.shape).astype(np.float32), d.astype(np.float32)


def diffuse_directions(normals, rng):
    """Cosine-weighted directions about unit ``normals``: normal + a uniform unit vector."""
    u = rng.normal(size=normals.shape)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    d = normals + u
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d.astype(np.float32)


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--threads", type=int, default=os.cpu_count())
    ap.add_argument("--width", type=int, default=1024)
    ap.add_argument("--height", type=int, default=768)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--accel", default=None, help="rayd accelerator (default: auto)")
    ap.add_argument("--precision", default=None,
                    help="rayd ray/triangle test, fast or watertight (default: the server's, watertight)")
    ap.add_argument("--url", help="an already running server (its --threads is yours to match)")
    ap.add_argument("--rayd-bin", type=Path, default=REPO / "target" / "release" / "rayd")
    args = ap.parse_args()

    import open3d as o3d  # late: the script's --help works without it

    server = None
    data = tempfile.TemporaryDirectory(prefix="rayd-bench-")
    if args.url:
        url = args.url
    else:
        port = free_port()
        url = f"http://127.0.0.1:{port}"
        server = subprocess.Popen(
            [str(args.rayd_bin), "serve", "--addr", f"127.0.0.1:{port}", "--data-dir",
             data.name, "--threads", str(args.threads), "--max-client-requests", "0"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            env={**os.environ, "RAYD_LOG": "warn"},
        )
    try:
        client = rayd.Client(url, timeout=600)
        client.wait_ready(60)
        source = client.upload(args.scene)
        tris = np.asarray(source.triangles(), np.float32)
        lo, hi = tris.reshape(-1, 3).min(0), tris.reshape(-1, 3).max(0)
        all_tris = np.concatenate([tris, room_around(lo, hi)])
        scene = client.upload(bytes(formats.encode_triangles(all_tris)))

        origins, directions = camera_rays(lo.astype(np.float64), hi.astype(np.float64),
                                          args.width, args.height)
        primary = scene.trace(origins, directions, accel=args.accel)
        if not (primary["prim"] != rayd.INVALID_ID).all():
            sys.exit("a camera ray left the room: the scene's bounds are odd")
        normals = rayd.face_normals(all_tris, primary["prim"])
        normals[np.einsum("ij,ij->i", normals, directions) > 0] *= -1
        rng = np.random.default_rng(args.seed)
        spawned = rayd.spawn_rays(primary, diffuse_directions(normals, rng), all_tris)
        o, d = spawned["origins"], spawned["directions"]
        rays6 = np.ascontiguousarray(np.concatenate([o, d], axis=1), dtype=np.float32)
        n = len(rays6)

        # rayd through the client: one warm-up (the structure is built and cached), then runs.
        build_ms = primary.server_timing.get("build", float("nan"))  # the first trace built
        scene.trace(o, d, accel=args.accel, precision=args.precision)
        server_ms = []

        def rayd_trace():
            h = scene.trace(o, d, accel=args.accel, precision=args.precision)
            server_ms.append(h.server_timing.get("trace", float("nan")))
            return h

        t_trace, hits = timed(rayd_trace, args.runs)
        version = scene.version
        scene.cast_rays(rays6[:1024], accel=args.accel, version=version, precision=args.precision)  # triangles fetched
        t_cast, ours = timed(
            lambda: scene.cast_rays(rays6, accel=args.accel, version=version, precision=args.precision), args.runs
        )

        # Open3D in process, same triangles, same rays, same threads.
        o3 = o3d.t.geometry.RaycastingScene(nthreads=args.threads)
        o3.add_triangles(
            o3d.core.Tensor(all_tris.reshape(-1, 3)),
            o3d.core.Tensor(np.arange(3 * len(all_tris), dtype=np.uint32).reshape(-1, 3)),
        )
        o3.cast_rays(o3d.core.Tensor(rays6[:1024]), nthreads=args.threads)  # builds the BVH

        def open3d_cast():
            ans = o3.cast_rays(o3d.core.Tensor(rays6), nthreads=args.threads)
            return {k: v.numpy() for k, v in ans.items()}

        t_o3d, theirs = timed(open3d_cast, args.runs)
    finally:
        if server is not None:
            server.send_signal(signal.SIGTERM)
            try:
                server.wait(timeout=20)
            except subprocess.TimeoutExpired:
                server.kill()
        data.cleanup()

    same_prim = float((theirs["primitive_ids"] == ours["primitive_ids"]).mean())
    both = np.isfinite(theirs["t_hit"]) & np.isfinite(ours["t_hit"])
    rel = np.abs(theirs["t_hit"][both] - ours["t_hit"][both]) / np.maximum(
        np.abs(ours["t_hit"][both]), 1e-30)
    accel = hits.accel
    print(f"scene {args.scene.name}: {len(tris)} triangles + 12 of the room; {n} diffuse rays "
          f"({args.width}x{args.height}, bounce 1, all hit); threads {args.threads}; "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} cpus; "
          f"rayd accel {accel}, precision {args.precision or 'watertight'} (build {build_ms:.1f} ms in the primary trace, untimed); open3d {o3d.__version__}; "
          f"median of {args.runs}; load {os.getloadavg()[0]:.1f}")
    print()
    print("| tracer | what is timed | ms | Mray/s |")
    print("|---|---|---:|---:|")
    print(f"| rayd client `Scene.trace` | numpy in, t/prim/u/v numpy out, over HTTP | "
          f"{t_trace * 1e3:.1f} | {n / t_trace / 1e6:.2f} |")
    print(f"| rayd client `Scene.cast_rays` | the same plus Open3D's arrays and normals | "
          f"{t_cast * 1e3:.1f} | {n / t_cast / 1e6:.2f} |")
    srv = statistics.median(server_ms)
    print(f"| rayd server alone | `Server-Timing` trace (inside the service) | "
          f"{srv:.1f} | {n / (srv / 1e3) / 1e6:.2f} |")
    print(f"| Open3D `RaycastingScene.cast_rays` | in process, `.numpy()` included | "
          f"{t_o3d * 1e3:.1f} | {n / t_o3d / 1e6:.2f} |")
    print()
    print(f"same triangle hit: {100 * same_prim:.3f}% of rays; relative t difference where "
          f"both hit: median {np.median(rel):.2e}, max {rel.max():.2e}")


if __name__ == "__main__":
    main()
