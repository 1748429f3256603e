#!/usr/bin/env python3
"""Times synchronous traces whose bodies arrive slowly, as over a real network, with the
server's accelerator `dacrt`, `mbvh8` and `auto` in turn (BENCHMARKS.md §12.11).

Starts `rayd serve` (2 threads) on a free loopback port with a temporary data directory,
uploads SCENE, then sends RAYS (a RAY1 file) as the body of `POST /v1/scenes/{id}/trace`
at RATE bytes per second (the client sleeps between 128 KiB pieces), each request a new
animation time (`version=1&time=…`, new geometry every frame). Prints the median time from
the request's first byte to the answer's last, per accelerator, and what `auto` ran.

    scripts/slow_upload.py ../shared/scenes/CesiumMan.glb /tmp/rays/cesium-frame-256k.ray \\
        --rate 80e6 --requests 6
"""

import argparse
import json
import socket
import statistics
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def request(port, path, body, rate):
    """One POST at `rate` bytes/s; returns (seconds, response head)."""
    s = socket.create_connection(("127.0.0.1", port))
    head = (f"POST {path} HTTP/1.1\r\nHost: x\r\nContent-Type: application/octet-stream\r\n"
            f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n")
    s.sendall(head.encode())
    t0 = time.perf_counter()
    step = 1 << 17
    for i in range(0, len(body), step):
        s.sendall(body[i:i + step])
        wait = t0 + (i + step) / rate - time.perf_counter()
        if wait > 0:
            time.sleep(wait)
    data = bytearray()
    while True:
        chunk = s.recv(1 << 20)
        if not chunk:
            break
        data += chunk
    seconds = time.perf_counter() - t0
    s.close()
    head = bytes(data).split(b"\r\n\r\n", 1)[0].decode()
    if " 200 " not in head.split("\r\n")[0]:
        raise SystemExit(f"{path}: {head}")
    return seconds, head


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("rays")
    ap.add_argument("--rate", type=float, default=80e6, help="upload bytes per second")
    ap.add_argument("--requests", type=int, default=6)
    ap.add_argument("--bin", default=str(ROOT / "target" / "release" / "rayd"))
    a = ap.parse_args()
    body = Path(a.rays).read_bytes()
    port = free_port()
    with tempfile.TemporaryDirectory() as data:
        server = subprocess.Popen(
            [a.bin, "serve", "--addr", f"127.0.0.1:{port}", "--data-dir", data,
             "--threads", "2"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            base = f"http://127.0.0.1:{port}"
            for _ in range(200):
                try:
                    urllib.request.urlopen(base + "/readyz")
                    break
                except OSError:
                    time.sleep(0.05)
            req = urllib.request.Request(
                base + "/v1/scenes", data=Path(a.scene).read_bytes(),
                headers={"Content-Type": "model/gltf-binary"})
            sid = json.load(urllib.request.urlopen(req))["id"]
            times = {k: [] for k in ["dacrt", "mbvh8", "auto"]}
            ran = []
            n = 0
            for _ in range(a.requests):
                for accel in times:
                    n += 1
                    t = 0.001 * n
                    path = f"/v1/scenes/{sid}/trace?accel={accel}&version=1&time={t:.6f}"
                    seconds, head = request(port, path, body, a.rate)
                    times[accel].append(seconds)
                    if accel == "auto":
                        ran += [line.split(":", 1)[1].strip() for line in head.split("\r\n")
                                if line.lower().startswith("x-rayd-accel")]
            mb = len(body) / 1e6
            print(f"| {Path(a.scene).name} | {mb:.1f} MB at {a.rate / 1e6:.0f} MB/s | "
                  + " | ".join(f"{statistics.median(v) * 1e3:.1f}" for v in times.values())
                  + f" | {', '.join(ran)} |")
        finally:
            server.terminate()
            server.wait()


if __name__ == "__main__":
    main()
