#!/usr/bin/env python3
"""Where a warm HTTP trace's time and CPU go (BENCHMARKS §12.8).

Starts `BIN serve --threads T` on a free loopback port with a temporary data directory,
uploads SCENE, sends RAYS (a RAY1 file, e.g. from `rayd bench --dump`) as warm traces with
a plain socket client (one `sendall` of the body, the answer read into a buffer of its
`Content-Length`), and prints the median upload / wait / response / total times and the
server's `Server-Timing` build and trace. With `--perf`, the timed requests run under `perf record`
of the server and the script also prints the server's core-ms per request by thread name
(the rayon pool, the tokio HTTP threads, the trace's own thread), from the sample counts.

    scripts/http_trace_cpu.py SCENE RAYS [--bin target/release/rayd] [--threads 2]
        [--requests 20] [--accel mbvh8] [--new-times] [--gap S] [--keep-alive]
        [--server-log FILE]
        [--perf [--perf-out FILE]]
"""
import argparse
import collections
import contextlib
import json
import os
import shutil
import socket
import statistics
import subprocess
import tempfile
import time

FREQ = 2999


@contextlib.contextmanager
def serve(binary, threads, log=subprocess.DEVNULL, extra=()):
    """`BINARY serve --threads THREADS [EXTRA...]` on a free loopback port with a temporary
    data directory, once it accepts connections: yields (port, process, data directory)
    and kills it at the end."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    with tempfile.TemporaryDirectory() as data:
        server = subprocess.Popen(
            [binary, "serve", "--threads", str(threads), "--data-dir", data,
             "--addr", f"127.0.0.1:{port}", *extra],
            stdout=subprocess.DEVNULL, stderr=log)
        try:
            for _ in range(100):
                try:
                    socket.create_connection(("127.0.0.1", port)).close()
                    break
                except OSError:
                    time.sleep(0.05)
            yield port, server, data
        finally:
            server.kill()
            server.wait()


def request(port, method, path, body, ctype, conn=None, rate=None):
    """One request on a new connection, or on `conn` (an open socket, kept open):
    (answer body, header dict, phase seconds). With `rate`, the body goes in 128 KiB pieces
    at about `rate` bytes per second, as over a slow link."""
    t0 = time.perf_counter()
    s = conn
    if s is None:
        s = socket.create_connection(("127.0.0.1", port))
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    close = "close" if conn is None else "keep-alive"
    s.sendall(f"{method} {path} HTTP/1.1\r\nHost: x\r\nConnection: {close}\r\n"
              f"Content-Length: {len(body)}\r\nContent-Type: {ctype}\r\n\r\n".encode())
    if rate is None:
        s.sendall(body)
    else:
        step = 1 << 17
        for i in range(0, len(body), step):
            s.sendall(body[i:i + step])
            wait = t0 + (i + step) / rate - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
    t1 = time.perf_counter()
    head = bytearray()
    while b"\r\n\r\n" not in head:
        chunk = s.recv(1 << 16)
        if not chunk:
            raise RuntimeError(f"{path}: the connection closed before the head")
        head += chunk
    t2 = time.perf_counter()
    k = head.index(b"\r\n\r\n")
    lines = bytes(head[:k]).decode().split("\r\n")
    headers = {l.split(":", 1)[0].strip().lower(): l.split(":", 1)[1].strip()
               for l in lines[1:]}
    length = int(headers["content-length"])
    out = bytearray(length)
    view = memoryview(out)
    have = len(head) - k - 4
    view[:have] = head[k + 4:]
    while have < length:
        n = s.recv_into(view[have:])
        if n == 0:
            break
        have += n
    t3 = time.perf_counter()
    if conn is None:
        s.close()
    if not lines[0].split()[1].startswith("2"):
        raise RuntimeError(f"{path}: {lines[0]} {bytes(out[:300])!r}")
    return out, headers, (t1 - t0, t2 - t1, t3 - t2, t3 - t0)


def wait_thumbnail(port, scene_id):
    """Waits for scene `scene_id`'s thumbnail, the render every upload queues at the lowest
    priority, so that timed work does not share the pool with it (the route answers 409
    while it is still to come)."""
    for _ in range(120):
        try:
            request(port, "GET", f"/v1/scenes/{scene_id}/thumbnail", b"",
                    "application/octet-stream")
            return
        except RuntimeError as e:
            if " 409 " not in str(e):
                raise


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("rays")
    ap.add_argument("--bin", default="target/release/rayd")
    ap.add_argument("--threads", default="2")
    ap.add_argument("--requests", type=int, default=20)
    ap.add_argument("--accel", default="mbvh8")
    ap.add_argument("--perf", action="store_true")
    ap.add_argument("--perf-out", help="keep the perf record here (for perf report -i)")
    ap.add_argument("--new-times", action="store_true",
                    help="each timed request a new time= of version 1 (an animated frame)")
    ap.add_argument("--gap", type=float, default=0.0,
                    help="seconds the server sits idle before each timed request")
    ap.add_argument("--keep-alive", action="store_true",
                    help="the timed requests share one connection, as a client session does")
    ap.add_argument("--server-log", help="the server's stderr goes here (else nowhere)")
    args = ap.parse_args()
    body = open(args.rays, "rb").read()
    log = open(args.server_log, "w") if args.server_log else subprocess.DEVNULL
    with serve(args.bin, args.threads, log) as (port, server, data):
        scene, _, _ = request(port, "POST", "/v1/scenes", open(args.scene, "rb").read(),
                              "model/gltf-binary")
        path = f"/v1/scenes/{json.loads(bytes(scene))['id']}/trace?accel={args.accel}"
        for _ in range(3):  # warm: the structure is built and cached
            request(port, "POST", path, body, "application/octet-stream")
        perf_data = os.path.join(data, "perf.data")
        perf = None
        if args.perf:
            perf = subprocess.Popen(
                ["perf", "record", "-q", "-F", str(FREQ), "-p", str(server.pid),
                 "-o", perf_data], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            time.sleep(0.5)
        phases, traces, builds = [], [], []
        conn = None
        if args.keep_alive:
            conn = socket.create_connection(("127.0.0.1", port))
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        for k in range(args.requests):
            time.sleep(args.gap)
            timed = f"{path}&version=1&time={0.01 * (k + 1):.2f}" if args.new_times else path
            _, h, t = request(port, "POST", timed, body, "application/octet-stream", conn)
            phases.append(t)
            timing = h["server-timing"]
            traces.append(float(timing.split("trace;dur=")[1]))
            builds.append(float(timing.split("build;dur=")[1].split(",")[0]))
        if perf:
            perf.send_signal(2)
            perf.wait()
            if args.perf_out:
                shutil.copy(perf_data, args.perf_out)
        med = [statistics.median(c) * 1e3 for c in zip(*phases)]
        print(f"{args.bin}: {args.requests} requests, ms (median): upload {med[0]:.1f}, "
              f"wait {med[1]:.1f}, response {med[2]:.1f}, total {med[3]:.1f}; "
              f"Server-Timing build {statistics.median(builds):.2f}, "
              f"trace {statistics.median(traces):.1f}")
        if perf:
            report = subprocess.run(
                ["perf", "report", "-i", perf_data, "-n", "--no-children", "--sort", "comm",
                 "--stdio", "-g", "none"], capture_output=True, text=True).stdout
            by_name = collections.Counter()
            for line in report.splitlines():
                parts = line.split()
                if len(parts) == 3 and parts[0].endswith("%") and not line.startswith("#"):
                    by_name[parts[2]] += int(parts[1])
            per = {k: v / FREQ * 1e3 / args.requests for k, v in by_name.items()}
            print("server core-ms per request: " + ", ".join(
                f"{k} {v:.2f}" for k, v in sorted(per.items(), key=lambda kv: -kv[1])
                if v >= 0.05) + f"; total {sum(per.values()):.1f}")


if __name__ == "__main__":
    main()
