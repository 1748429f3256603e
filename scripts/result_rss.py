#!/usr/bin/env python3
"""The server's peak RSS while clients download a large job result (BENCHMARKS.md §29).

For each BIN: starts `BIN serve --threads 2` on a temporary data directory, uploads SCENE,
makes one asynchronous trace job of RAYS rays (`Prefer: respond-async`, `hit=t_prim_uv`:
16 bytes a ray) and waits for it; then restarts the server on the same directory, so that
the job's own memory is not in the peak, and has CLIENTS clients download the result at
once, ROUNDS times. Prints the peak RSS (`VmHWM`) after the restart and after the
downloads, and the median download time.

    scripts/result_rss.py SCENE --bin OLD --bin NEW [--rays 4000000] [--clients 4]
        [--rounds 3]
"""
import argparse
import json
import os
import socket
import statistics
import struct
import subprocess
import tempfile
import threading
import time

from http_trace_cpu import request, wait_thumbnail


def start(binary, data):
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    server = subprocess.Popen(
        [binary, "serve", "--threads", "2", "--data-dir", data, "--addr", f"127.0.0.1:{port}"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    for _ in range(200):
        try:
            socket.create_connection(("127.0.0.1", port)).close()
            return port, server
        except OSError:
            time.sleep(0.05)
    raise RuntimeError(f"{binary} serve did not start")


def peak_mib(pid):
    for line in open(f"/proc/{pid}/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmHWM")


def rays_body(n, lo, hi):
    """RAY1: n rays from random points of the box towards random directions."""
    import numpy as np
    rng = np.random.default_rng(7)
    rec = np.zeros((n, 8), dtype="<f4")
    rec[:, 0:3] = rng.uniform(lo, hi, size=(n, 3))
    rec[:, 4:7] = rng.uniform(-1, 1, size=(n, 3))
    rec[:, 7] = np.inf
    return struct.pack("<4sHHQ", b"RAY1", 1, 0, n) + rec.tobytes()


def measure(binary, scene, body, clients, rounds):
    with tempfile.TemporaryDirectory() as data:
        port, server = start(binary, data)
        try:
            up, _, _ = request(port, "POST", "/v1/scenes", open(scene, "rb").read(),
                               "model/gltf-binary")
            sid = json.loads(bytes(up))["id"]
            wait_thumbnail(port, sid)
            s = socket.create_connection(("127.0.0.1", port))
            head = (f"POST /v1/scenes/{sid}/trace?hit=t_prim_uv HTTP/1.1\r\nHost: x\r\n"
                    f"Connection: close\r\nPrefer: respond-async\r\n"
                    f"Content-Type: application/octet-stream\r\n"
                    f"Content-Length: {len(body)}\r\n\r\n")
            s.sendall(head.encode() + body)
            answer = b""
            while chunk := s.recv(1 << 16):
                answer += chunk
            s.close()
            job = json.loads(answer.split(b"\r\n\r\n", 1)[1])["id"]
            while True:
                j, _, _ = request(port, "GET", f"/v1/jobs/{job}", b"", "application/json")
                state = json.loads(bytes(j))["state"]
                if state in ("succeeded", "failed", "cancelled"):
                    break
                time.sleep(0.2)
            assert state == "succeeded", state
        finally:
            server.kill()
            server.wait()
        port, server = start(binary, data)
        try:
            request(port, "GET", "/v1/jobs", b"", "application/json")
            before = peak_mib(server.pid)
            took, size = [], [0]

            def fetch():
                r, _, phases = request(port, "GET", f"/v1/jobs/{job}/result", b"",
                                       "application/octet-stream")
                size[0] = len(r)
                took.append(phases[3])

            for _ in range(rounds):
                threads = [threading.Thread(target=fetch) for _ in range(clients)]
                for t in threads:
                    t.start()
                for t in threads:
                    t.join()
            after = peak_mib(server.pid)
        finally:
            server.kill()
            server.wait()
    return before, after, size[0], statistics.median(took)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--bin", action="append", required=True)
    ap.add_argument("--rays", type=int, default=4_000_000)
    ap.add_argument("--clients", type=int, default=4)
    ap.add_argument("--rounds", type=int, default=3)
    a = ap.parse_args()
    body = rays_body(a.rays, (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    print(f"load average {os.getloadavg()[0]:.2f}; {a.rays} rays, {a.clients} clients x "
          f"{a.rounds} rounds\n")
    print("| binary | result MiB | peak RSS after restart | peak RSS after downloads | "
          "median download |")
    print("|---|---:|---:|---:|---:|")
    for b in a.bin:
        before, after, size, took = measure(b, a.scene, body, a.clients, a.rounds)
        print(f"| {b} | {size / 2**20:.1f} | {before:.1f} MiB | {after:.1f} MiB | "
              f"{took * 1e3:.0f} ms |")


if __name__ == "__main__":
    main()
