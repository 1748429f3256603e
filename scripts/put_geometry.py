#!/usr/bin/env python3
"""Times `PUT /v1/scenes/{id}/geometry` alone (BENCHMARKS.md §12.13): the geometry update of
a `PUT` + trace frame, without the trace.

Starts `rayd serve` (2 threads) with a temporary data directory (`http_trace_cpu.py`'s
server and client), uploads SCENE, reads its triangles back (`GET …/geometry`, TRI1), then
sends them as REQUESTS geometry updates on one kept connection. Each update moves the first
vertex a little, so that every one is a new blob (written, fsynced and renamed, its
directory fsynced, its version committed) as a frame's new positions are. With `--gap S`
the server idles S seconds before each. Prints the median, fastest and slowest update of
all but the first ten. With `--strace`, the updates run under `strace -f -T` of the server
and the script also prints how long its fsyncs took: the blob's (the one before each
rename), its directory's (the one after) and the others (the database's commit, and the
directory of each blob shard made for the first time). At the end it prints the bytes under
the data directory (blobs and database), a second after the last update, and how many
blob files there are: with `--keep-versions K` (anything after `--` goes to `rayd serve`)
they stay near K versions' worth.

    scripts/put_geometry.py ../shared/scenes/CesiumMan.glb [--requests 60] [--gap 0.05]
        [--strace] [--bin target/release/rayd] [-- --keep-versions 16]
"""
import argparse
import json
import os
import re
import signal
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import time

from http_trace_cpu import request, serve

TRI = "application/x-rayd-tri"
HEADER = 16  # TRI1: magic, version, format, triangle count; then 36-byte records


def fsyncs(trace):
    """The durations (ms) of the fsyncs in an `strace -T` log, by what they made durable."""
    lines = open(trace).read().splitlines()
    kinds = {"blob": [], "its directory": [], "others": []}
    for i, line in enumerate(lines):
        took = re.search(r"<([0-9.]+)>$", line)
        if "fsync(" not in line or not took:
            continue
        if i + 1 < len(lines) and "renameat2(" in lines[i + 1]:
            kind = "blob"
        elif i > 0 and "renameat2(" in lines[i - 1]:
            kind = "its directory"
        else:
            kind = "others"
        kinds[kind].append(float(took.group(1)) * 1e3)
    return kinds


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--requests", type=int, default=60)
    ap.add_argument("--gap", type=float, default=0.0)
    ap.add_argument("--strace", action="store_true")
    ap.add_argument("--perf", metavar="FILE",
                    help="record the server's CPU during the updates with `perf record -g` into FILE")
    ap.add_argument("--bin", default="target/release/rayd")
    argv = sys.argv[1:]
    cut = argv.index("--") if "--" in argv else len(argv)
    a = ap.parse_args(argv[:cut])
    a.serve_args = argv[cut + 1:]  # more `rayd serve` options
    log = os.path.join(tempfile.mkdtemp(), "put.strace")
    with serve(a.bin, 2, extra=a.serve_args) as (port, server, data):
        scene, _, _ = request(port, "POST", "/v1/scenes", open(a.scene, "rb").read(),
                              "model/gltf-binary")
        sid = json.loads(bytes(scene))["id"]
        tri, _, _ = request(port, "GET", f"/v1/scenes/{sid}/geometry", b"", TRI)
        conn = socket.create_connection(("127.0.0.1", port))
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        y = HEADER + 4  # the first vertex's y
        tracer = None
        if a.strace:
            tracer = subprocess.Popen(
                ["strace", "-f", "-T", "-e", "trace=fsync,renameat2", "-o", log,
                 "-p", str(server.pid)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            time.sleep(0.5)
        if a.perf:
            tracer = subprocess.Popen(
                ["perf", "record", "-q", "-g", "-o", a.perf, "-p", str(server.pid)],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            time.sleep(0.5)
        ms = []
        for _ in range(a.requests):
            struct.pack_into("<f", tri, y, struct.unpack_from("<f", tri, y)[0] + 1e-4)
            time.sleep(a.gap)
            _, _, phases = request(port, "PUT", f"/v1/scenes/{sid}/geometry", bytes(tri), TRI,
                                   conn=conn)
            ms.append(phases[3] * 1e3)
        if tracer:
            if a.perf:
                tracer.send_signal(signal.SIGINT)
            else:
                tracer.terminate()
            tracer.wait()
        time.sleep(1.0)
        stored = sum(os.path.getsize(os.path.join(root, f))
                     for root, _, files in os.walk(data) for f in files)
        shards = os.path.join(data, "blobs")
        blobs = sum(len([f for f in os.listdir(os.path.join(shards, d)) if not f.startswith(".")])
                    for d in os.listdir(shards) if len(d) == 2)
    timed = ms[10:]
    print(f"{a.bin}: {len(timed)} geometry updates ({len(tri)} bytes), gap {a.gap} s: "
          f"median {statistics.median(timed):.2f} ms, fastest {min(timed):.2f}, "
          f"slowest {max(timed):.2f}")
    print(f"  data directory: {stored / 2**20:.1f} MiB, {blobs} blob files "
          f"(extra serve options: {' '.join(a.serve_args) or 'none'})")
    if a.strace:
        for kind, took in fsyncs(log).items():
            if took:
                print(f"  fsync, {kind}: {len(took)}, median {statistics.median(took):.2f} ms, "
                      f"{min(took):.2f}-{max(took):.2f}")


if __name__ == "__main__":
    main()
