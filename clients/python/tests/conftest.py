"""Fixtures: a real ``rayd serve`` for the session, and the ``rayd`` binary for references.

The server is the binary named by ``RAYD_BIN`` (default ``target/release/rayd`` under the
repository root), started on a free loopback port with a temporary data directory and the
demo scenes, and stopped (SIGTERM, then SIGKILL) at the end. Tests that need it are skipped
with a message when the default binary has not been built; a ``RAYD_BIN`` that names no
file is an error, so CI cannot skip by accident.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import tempfile
from pathlib import Path

import pytest

import rayd

REPO = Path(__file__).resolve().parents[3]
SCENES = REPO / "scenes"


def _binary() -> Path | None:
    named = os.environ.get("RAYD_BIN")
    if named:
        path = Path(named)
        if not path.is_absolute():
            path = REPO / path
        if not path.is_file():
            raise FileNotFoundError(f"RAYD_BIN={named} names no file")
        return path
    path = REPO / "target" / "release" / "rayd"
    return path if path.is_file() else None


@pytest.fixture(scope="session")
def rayd_bin() -> Path:
    path = _binary()
    if path is None:
        pytest.skip("target/release/rayd is not built (cargo build --release) and RAYD_BIN is unset")
    return path


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """A running ``rayd serve``: its URL, data directory and log."""

    def __init__(self, binary: Path, data_dir: Path, *args: str, port: int | None = None):
        # ``port``: that of a server stopped before, to start it again where it was.
        self.port = _free_port() if port is None else port
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_path = data_dir.parent / f"serve-{self.port}.log"
        self._log = open(self.log_path, "ab")
        self.proc = subprocess.Popen(
            [str(binary), "serve", "--addr", f"127.0.0.1:{self.port}",
             "--data-dir", str(data_dir), *args],
            stdout=self._log,
            stderr=subprocess.STDOUT,
            env={**os.environ, "RAYD_LOG": "warn"},
        )

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def wait_ready(self, client: rayd.Client):
        try:
            client.wait_ready(timeout=60)
        except TimeoutError:
            self.stop()
            raise RuntimeError(f"rayd serve did not become ready:\n{self.log()}") from None

    def stop(self):
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()


@pytest.fixture(scope="session")
def workdir():
    with tempfile.TemporaryDirectory(prefix="rayd-pytest-") as d:
        yield Path(d)


@pytest.fixture(scope="session")
def server(rayd_bin, workdir):
    data = workdir / "data"
    srv = Server(rayd_bin, data, "--demo", "--max-client-requests", "0")
    srv.wait_ready(rayd.Client(srv.url))
    yield srv
    srv.stop()
    assert srv.proc.returncode == 0, f"rayd serve exited {srv.proc.returncode}:\n{srv.log()}"


@pytest.fixture(scope="session")
def client(server) -> rayd.Client:
    return rayd.Client(server.url, timeout=120)


@pytest.fixture(scope="session")
def fox(client) -> rayd.Scene:
    """Fox.glb (skinned, animated; the demo uploaded it, so this upload finds it)."""
    return client.upload(SCENES / "Fox.glb")
