"""Refusals and failures that the real server shows only in races: a frame refused for its
rays after its version was made, an event stream answered 503 or left silent, a body cut
off half-way. A scripted stand-in answers each request as the case needs, and logs what
it was sent.
"""

from __future__ import annotations

import json
import socket
import threading
import time

import numpy as np
import pytest
import requests

import rayd
from helpers import read_request
from rayd import client as client_module
from rayd import formats

SCENE = "ab12"
SUMMARY = {"id": SCENE, "version": 1, "created_at": 1, "triangles": 1, "content_type":
           "application/x-rayd-tri", "bounds": {"min": [0, 0, 0], "max": [1, 1, 0]}}
JOB = {"id": "0123", "kind": "render", "state": "running", "progress": 0.5}
ORIGIN = np.zeros((1, 3), np.float32)
DOWN = np.array([[0, 0, -1]], np.float32)
TRIS = np.zeros((1, 3, 3), np.float32)


def _response(status: str, body: bytes, ctype="application/json", extra="") -> bytes:
    # The stand-in closes every connection after its answer, and says so: a client that
    # sent its next request on the closed connection would meet a reset.
    return (f"HTTP/1.1 {status}\r\nContent-Type: {ctype}\r\nContent-Length: {len(body)}\r\n"
            f"Connection: close\r\n{extra}\r\n").encode() + body


def _problem(status: int, title: str, **extras) -> bytes:
    doc = {"type": "/problems/unavailable", "title": title, "status": status,
           "detail": title, **extras}
    return _response(f"{status} {title}", json.dumps(doc).encode(),
                     "application/problem+json", "Retry-After: 0\r\n")


class ScriptedServer:
    """Answers each request with ``script(method, path)``: bytes to send (then the
    connection closes), or None to send nothing and hold the connection open. ``log`` is
    ``(method, path)`` for every request read."""

    def __init__(self, script):
        self.script = script
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self._listener.getsockname()[1]}"
        self.log: list[tuple[str, str]] = []
        self._held: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def close(self):
        self._listener.close()
        for c in self._held:
            c.close()

    def _accept(self):
        while True:
            try:
                conn, _ = self._listener.accept()
            except OSError:
                return
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn):
        request = read_request(conn.makefile("rb"))
        if request is None:
            conn.close()
            return
        method, path, _, _ = request
        self.log.append((method, path))
        out = self.script(method, path)
        if out is None:
            self._held.append(conn)  # silent, open
            return
        conn.sendall(out)
        conn.close()


@pytest.fixture
def scripted():
    servers = []

    def start(script):
        srv = ScriptedServer(script)
        servers.append(srv)
        return srv

    yield start
    for s in servers:
        s.close()


def test_a_frame_refused_after_making_its_version_is_not_sent_again(scripted):
    def script(method, path):
        if method == "POST" and path.endswith("/frame"):
            return _problem(503, "Service Unavailable", version=2)
        return _response("200 OK", json.dumps(SUMMARY).encode())

    srv = scripted(script)
    scene = rayd.Client(srv.url, timeout=10, retries=3).scene(SCENE)
    with pytest.raises(rayd.ProblemError) as e:
        scene.frame(TRIS, ORIGIN, DOWN)
    assert e.value.status == 503 and e.value.version == 2
    assert [m for m, p in srv.log if p.endswith("/frame")] == ["POST"], "sent once"
    assert scene.info["version"] == 2, "the version the refusal names is noted"


def test_a_refusal_that_made_nothing_is_still_retried(scripted):
    tries = []

    def script(method, path):
        if method == "POST" and path.endswith("/trace"):
            tries.append(1)
            if len(tries) == 1:
                return _problem(503, "Service Unavailable")
            hit1 = formats.header(formats.HIT1_MAGIC, 0, 1) + b"\0" * 16
            return _response("200 OK", hit1, "application/octet-stream")
        return _response("200 OK", json.dumps(SUMMARY).encode())

    srv = scripted(script)
    scene = rayd.Client(srv.url, timeout=10, retries=3).scene(SCENE)
    scene.trace(ORIGIN, DOWN)
    assert len(tries) == 2


def test_wait_polls_when_the_event_stream_is_refused(scripted):
    polls = []

    def script(method, path):
        if path.endswith("/events"):
            return _problem(503, "Service Unavailable")
        polls.append(1)
        state = "succeeded" if len(polls) > 2 else "running"
        return _response("200 OK", json.dumps({**JOB, "state": state}).encode())

    srv = scripted(script)
    job = rayd.Job(rayd.Client(srv.url, timeout=10, retries=3), dict(JOB))
    t0 = time.monotonic()
    job.wait(progress=False, timeout=20)
    assert job.info["state"] == "succeeded"
    assert [p for _, p in srv.log].count(f"/v1/jobs/{JOB['id']}/events") == 1, "not retried"
    assert time.monotonic() - t0 < 10


def test_wait_gives_up_on_a_stream_that_stays_silent(scripted, monkeypatch):
    # The server's keep-alives come every _KEEP_ALIVE_SECONDS; a stream silent for twice
    # that (or the client's timeout) is a server that hangs.
    monkeypatch.setattr(client_module, "_KEEP_ALIVE_SECONDS", 0.5)

    def script(method, path):
        if path.endswith("/events"):
            return None
        return _response("200 OK", json.dumps({**JOB, "state": "succeeded"}).encode())

    srv = scripted(script)
    job = rayd.Job(rayd.Client(srv.url, timeout=1.5), dict(JOB))
    t0 = time.monotonic()
    job.wait(progress=False)
    assert job.info["state"] == "succeeded"
    assert time.monotonic() - t0 < 10


def test_a_body_cut_off_is_a_requests_error(scripted):
    def script(method, path):
        if path.endswith("/result"):
            head = (b"HTTP/1.1 200 OK\r\nContent-Type: image/x-exr\r\n"
                    b"Content-Length: 100000\r\nConnection: close\r\n\r\n")
            return head + b"v/1\x01" + b"\0" * 1000  # then the connection closes
        return _response("200 OK", json.dumps({**JOB, "state": "succeeded"}).encode())

    srv = scripted(script)
    job = rayd.Job(rayd.Client(srv.url, timeout=10), {**JOB, "state": "succeeded"})
    with pytest.raises(requests.RequestException) as e:
        job.result(raw=True)
    assert "ended early" in str(e.value)
