"""The HTTP client: scenes, ray batches, geometry versions, render jobs.

Every route is the server's ``proto/openapi.yaml``; this module only turns numpy arrays
into request bodies and answers back into numpy arrays. Binary bodies go out as one
``bytearray`` (filled through a structured view, see :mod:`rayd.formats`) that the HTTP
library hands to the socket as it is, and come back as the one ``bytes`` object the socket
was read into, which the result arrays view. No per-ray Python code runs either way.

``requests`` is the HTTP library: the service is request/response plus one event stream,
which a synchronous, connection-pooling client covers; ``requests`` is the most widely
deployed and kept Python HTTP client, packaged everywhere, and through urllib3 it sends any
buffer-protocol body without copying it. (``httpx`` would add HTTP/2 and asyncio, which a
batch tracing client does not need.)
"""

from __future__ import annotations

import io
import json
import os
import time as _time
from collections import OrderedDict
from urllib.parse import quote

import numpy as np
import requests
import urllib3

from . import formats
from .errors import FormatError, JobError, ProblemError
from .formats import HIT_FORMATS, MISS_PRIM
from .spawn import triangle_normals

# Seconds between the keep-alive comments of the server's event streams.
_KEEP_ALIVE_SECONDS = 15

_FINAL = ("succeeded", "failed", "cancelled")
_MEDIA = {
    ".glb": "model/gltf-binary",
    ".gltf": "model/gltf+json",
    ".tri": "application/x-rayd-tri",
}
TRI_MEDIA = "application/x-rayd-tri"
_HIT_UV = np.dtype({"names": ["uv"], "formats": ["V8"], "offsets": [8], "itemsize": 16})
"""The ``u, v`` pair of a ``t_prim_uv`` HIT1 record as one 8-byte value."""
OCTET = "application/octet-stream"
FRAME_MEDIA = "application/x-rayd-frame"
"""A frame's body: TRI1 positions, then RAY1 rays."""
CACHED_VERSIONS = 4
"""How many geometry versions (a version and animation time each) a :class:`Scene` keeps
the positions and normals of. A frame loop needs the newest, a comparison of two versions
two; the server keeps 16 versions by default, and one that was dropped here is one
``GET …/geometry`` away, while keeping every version a client sends grows without end."""


class Hits(dict):
    """A trace's answer: the HIT1 fields as numpy arrays, keyed by name.

    ``t`` (float32, ``inf`` for a miss), ``prim`` (uint32, 0xFFFFFFFF for a miss), ``u`` and
    ``v`` (float32, 0 for a miss) for ``hit='t_prim_uv'``; ``t`` and ``prim`` for
    ``t_prim``; ``t`` for ``t``; ``occluded`` (bool) for ``occluded``. The arrays are
    read-only views of :attr:`body`, the HIT1 bytes exactly as the server sent them; copy
    one (``np.array(hits["t"])``) to write to it.

    ``accel`` is the accelerator that traced (what ``auto`` chose) and ``server_timing``
    the server's ``build`` and ``trace`` milliseconds, when the answer carried them;
    ``version`` the geometry version a :meth:`Scene.frame` made (None for other traces).
    """

    def __init__(self, body, records, accel=None, server_timing=None, version=None):
        super().__init__(formats.hit_arrays(records))
        self.body = body
        self.records = records
        self.accel = accel
        self.server_timing = server_timing or {}
        self.version = version


def open3d_answer(records, normals, lead=None, version=None) -> dict:
    """Open3D's ``cast_rays`` answer from ``t_prim_uv`` HIT1 ``records``: ``normals`` is one
    unit float32 normal per triangle plus a last zero row, ``lead`` the rays' leading shape
    (default: the records'), ``version`` the geometry traced (named in errors).

    Each output is one copy out of the records (no temporaries): ``geometry_ids`` by
    arithmetic on the miss mask, ``u, v`` copied as one 8-byte value a ray, and the
    normals gathered as 12-byte rows, the miss id 0xFFFFFFFF sent to the zero row by
    ``mode="clip"``. (12-13 ms for 786K rays against 14 for the construction this
    replaced: ``bench/open3d_answer.py``, BENCHMARKS §15.)"""
    lead = records.shape if lead is None else lead
    prim = np.array(records["prim"])
    miss = prim == MISS_PRIM
    # Clipping would hide an id past the table (a server answering for another
    # version): every id at or past its zero row must be a miss.
    if np.count_nonzero(prim >= normals.shape[0] - 1) != np.count_nonzero(miss):
        raise FormatError(
            f"HIT1: a triangle id at or past {normals.shape[0] - 1}, the triangle count "
            f"of version {version}"
        )
    gathered = np.take(normals.view("V12").reshape(-1), prim, mode="clip")
    ids = miss.astype(np.uint32)
    ids *= np.uint32(MISS_PRIM)
    uvs = np.array(records.view(_HIT_UV)["uv"])
    return {
        "t_hit": np.array(records["t"]).reshape(lead),
        "geometry_ids": ids.reshape(lead),
        "primitive_ids": prim.reshape(lead),
        "primitive_uvs": uvs.view("<f4").reshape(tuple(lead) + (2,)),
        "primitive_normals": gathered.view(np.float32).reshape(tuple(lead) + (3,)),
    }


def _server_timing(value: str | None) -> dict:
    """``build;dur=1.5, trace;dur=2.0`` as ``{"build": 1.5, "trace": 2.0}``."""
    out = {}
    for part in (value or "").split(","):
        name, _, rest = part.strip().partition(";")
        for p in rest.split(";"):
            k, _, v = p.strip().partition("=")
            if k == "dur" and name:
                try:
                    out[name] = float(v)
                except ValueError:
                    pass
    return out


def _dropped(err: requests.ConnectionError) -> bool:
    """Whether ``err`` is a connection that closed (or was reset) before any byte of the
    answer, as a pooled keep-alive connection does when the server closes it for being
    idle just as the request goes out; not a refused or timed-out connection."""
    reason = err.args[0] if err.args else None
    if not isinstance(reason, urllib3.exceptions.ProtocolError) or len(reason.args) < 2:
        return False
    # http.client's RemoteDisconnected ("closed connection without response") is a
    # ConnectionResetError.
    return isinstance(reason.args[1], (ConnectionResetError, ConnectionAbortedError,
                                       BrokenPipeError))


def _media_type_of(data: bytes) -> str | None:
    """The upload media type a body's first bytes show, if they show one."""
    head = bytes(data[:16])
    if head[:4] == b"glTF":
        return "model/gltf-binary"
    if len(head) >= 4 and int.from_bytes(head[:4], "little") == formats.TRI1_MAGIC:
        return TRI_MEDIA
    if head.lstrip(b"\xef\xbb\xbf \t\r\n")[:1] == b"{":
        return "model/gltf+json"
    return None


class Client:
    """A connection to one ``rayd serve``.

    ``url`` is the server's base URL; ``token`` a bearer token for servers started with
    ``--token-file``. ``timeout`` (seconds) bounds connecting and each wait for bytes.
    A 503 (queue full, body budget or per-client bound reached; always with
    ``Retry-After``) is retried up to ``retries`` times after the delay the server asks for;
    every other error status raises :class:`rayd.ProblemError`. A request that is safe to
    send again (a read, a synchronous trace, an upload, a job submitted with an
    idempotency key) is sent once more on a new connection when its connection closed
    before any byte of the answer: the server closes idle keep-alive connections, and one
    can close just as a request goes out on it.

    ``session`` may be shared with other code: the token goes with each request this
    client sends, never into the session's headers, so clients with other tokens (or
    none) can share it.
    """

    def __init__(
        self,
        url: str = "http://127.0.0.1:8080",
        token: str | None = None,
        *,
        timeout: float = 300.0,
        retries: int = 3,
        session: requests.Session | None = None,
    ):
        self.url = url.rstrip("/")
        self.timeout = timeout
        self.retries = retries
        self._http = session or requests.Session()
        self._auth = {} if token is None else {"Authorization": f"Bearer {token}"}

    def __repr__(self):
        return f"rayd.Client({self.url!r})"

    # -- plumbing -------------------------------------------------------------------------

    def _request(
        self,
        method: str,
        path: str,
        *,
        params=None,
        json_body=None,
        data=None,
        headers=None,
        stream=False,
        timeout=None,
        replay: bool | None = None,
        done_on_replay: tuple = (),
        retry: bool = True,
    ) -> requests.Response:
        """Sends one request, retrying a 503 with ``Retry-After`` (unless ``retry`` is
        False, or the refusal names a ``version``: a frame refused for its rays has made
        its version already, and sending it again would make another).

        ``replay`` says whether the request may be sent again when its connection closed
        before any answer (a pooled connection the server closed at its idle timeout);
        the default is yes for GET and HEAD only, since a request that makes something
        (a version, a job) could have been received and acted on. It is sent again once,
        on a new connection (urllib3 drops the dead one). ``done_on_replay`` are statuses
        that mean, on the replay, that the first sending did its work (a DELETE's 404):
        the response is returned instead of raised."""
        params = {k: v for k, v in (params or {}).items() if v is not None}
        headers = {**self._auth, **(headers or {})}
        if replay is None:
            replay = method in ("GET", "HEAD")
        replayed = False
        attempt = 0
        while True:
            try:
                resp = self._http.request(
                    method,
                    self.url + path,
                    params=params,
                    json=json_body,
                    data=data,
                    headers=headers,
                    stream=stream,
                    timeout=self.timeout if timeout is None else timeout,
                )
            except requests.ConnectionError as e:
                if replay and not replayed and _dropped(e):
                    replayed = True
                    continue
                raise
            if resp.status_code < 400:
                return resp
            if replayed and resp.status_code in done_on_replay:
                resp.close()
                return resp
            err = ProblemError.from_response(resp)
            resp.close()
            if (retry and resp.status_code == 503 and err.retry_after is not None
                    and "version" not in err.extras and attempt < self.retries):
                attempt += 1
                _time.sleep(min(max(err.retry_after, 0.05), 30.0))
                continue
            raise err

    def _json(self, method, path, **kw):
        resp = self._request(method, path, **kw)
        return resp.json() if resp.content else None

    def _binary(self, method, path, **kw):
        """A response and its whole body as one ``bytes``, read straight from the socket."""
        headers = {"Accept-Encoding": "identity", **(kw.pop("headers", None) or {})}
        resp = self._request(method, path, headers=headers, stream=True, **kw)
        try:
            body = resp.raw.read(decode_content=True)
        except urllib3.exceptions.HTTPError as e:
            # A body cut off half-way (the server went away) comes from urllib3 itself;
            # raise it as requests raises every other transport failure.
            raise requests.exceptions.ChunkedEncodingError(
                f"{method} {path}: the response ended early: {e}", response=resp
            ) from e
        finally:
            resp.raw.release_conn()
        return resp, body

    # -- the service ----------------------------------------------------------------------

    def wait_ready(self, timeout: float = 30.0) -> None:
        """Waits until ``/readyz`` answers 200 (the store is loaded and work is accepted)."""
        deadline = _time.monotonic() + timeout
        last = None
        while True:
            try:
                resp = self._http.get(self.url + "/readyz", headers=self._auth, timeout=2.0)
                if resp.status_code == 200:
                    return
                last = f"/readyz answered {resp.status_code}"
            except requests.ConnectionError as e:
                last = str(e)
            if _time.monotonic() > deadline:
                raise TimeoutError(f"{self.url} was not ready within {timeout} s: {last}")
            _time.sleep(0.05)

    def metrics(self) -> str:
        """The Prometheus text of ``/metrics``."""
        return self._request("GET", "/metrics").text

    # -- scenes ---------------------------------------------------------------------------

    def upload(self, path_or_bytes, *, content_type: str | None = None,
               name: str | None = None) -> Scene:
        """Uploads a scene: a path to a ``.glb``, ``.gltf`` (buffers embedded) or ``.tri``
        file, or the file's bytes. The media type comes from the extension or the bytes
        unless given. ``name`` names it in listings (1 to 1024 bytes, no control
        characters; bytes uploaded before keep their first name). Uploading the same bytes
        twice gives the same scene."""
        if isinstance(path_or_bytes, (str, os.PathLike)):
            path = os.fspath(path_or_bytes)
            with open(path, "rb") as f:
                data = f.read()
            content_type = content_type or _MEDIA.get(os.path.splitext(path)[1].lower())
            where = path
        else:
            data = path_or_bytes
            where = "the bytes given"
        content_type = content_type or _media_type_of(data)
        if content_type is None:
            raise ValueError(
                f"cannot tell the scene format of {where}: pass content_type= "
                f"({', '.join(sorted(set(_MEDIA.values())))})"
            )
        # Safe to send again: the same bytes make the same scene (the first one's, 200).
        info = self._json("POST", "/v1/scenes", data=data, replay=True,
                          params={"name": name}, headers={"Content-Type": content_type})
        scene = Scene(self, info)
        if content_type == TRI_MEDIA:
            # The positions of version 1 are the uploaded records themselves.
            scene._remember(1, None, formats.decode_triangles(bytes(data)))
        return scene

    def scene(self, scene_id: str) -> Scene:
        """The scene with this id."""
        return Scene(self, self._json("GET", f"/v1/scenes/{quote(scene_id, safe='')}"))

    def scenes(self) -> list[Scene]:
        """Every scene on the server (all pages)."""
        out, token = [], None
        while True:
            page = self._json("GET", "/v1/scenes", params={"limit": 1000, "page_token": token})
            out.extend(Scene(self, s) for s in page["scenes"])
            token = page.get("next_page_token")
            if not token:
                return out

    def delete(self, scene) -> None:
        """Deletes a scene (a :class:`Scene` or an id) and every version of it."""
        scene_id = scene.id if isinstance(scene, Scene) else scene
        if isinstance(scene, Scene):
            # Uploading the same bytes again makes a scene with this id whose versions
            # count from 1 again: nothing known of this one may answer for it.
            scene._known.clear()
        # Sent again if its connection closed unanswered; a 404 to that means the first
        # one deleted it.
        self._request("DELETE", f"/v1/scenes/{quote(scene_id, safe='')}",
                      replay=True, done_on_replay=(404,))

    # -- jobs -----------------------------------------------------------------------------

    def job(self, job_id: str) -> Job:
        """The job with this id."""
        return Job(self, self._json("GET", f"/v1/jobs/{quote(job_id, safe='')}"))

    def jobs(self) -> list[Job]:
        """Every job the server keeps, oldest first (all pages), as the server lists them."""
        out, token = [], None
        while True:
            page = self._json("GET", "/v1/jobs", params={"limit": 1000, "page_token": token})
            out.extend(Job(self, j) for j in page["jobs"])
            token = page.get("next_page_token")
            if not token:
                return out


class _Known:
    """Positions (and face normals) of the :data:`CACHED_VERSIONS` geometry versions used
    last, each a dict ``{"triangles": (T, 3, 3), "normals": (T + 1, 3)}``, the least
    recently used dropped first.

    Keys are ``(generation, version, time)``. Scene ids come from the uploaded bytes, so a
    scene deleted and uploaded again has the same id and versions counting from 1 again,
    with other positions from version 2 on: the generation is the scene's ``created_at``
    (which the new upload changes) for versions from 2 on, and None for version 1, which
    is the uploaded file itself and the same in every generation."""

    def __init__(self, size: int = CACHED_VERSIONS):
        self._entries: OrderedDict = OrderedDict()
        self.size = size

    def __len__(self):
        return len(self._entries)

    def get(self, key) -> dict | None:
        entry = self._entries.get(key)
        if entry is not None:
            self._entries.move_to_end(key)
        return entry

    def put(self, key, triangles) -> dict:
        entry = {"triangles": triangles}
        self._entries[key] = entry
        self._entries.move_to_end(key)
        while len(self._entries) > max(self.size, 1):
            self._entries.popitem(last=False)
        return entry

    def holds(self, version, time) -> bool:
        """Whether some generation's positions of ``version`` at ``time`` are here."""
        return any(k[1:] == (version, time) for k in self._entries)

    def keep_generation(self, generation) -> None:
        """Drops the entries of every other generation (version 1's stay)."""
        for key in [k for k in self._entries if k[1] != 1 and k[0] != generation]:
            del self._entries[key]

    def clear(self) -> None:
        self._entries.clear()


class Scene:
    """A scene on the server. ``info`` is its summary (``rayd info``'s fields, plus ``id``,
    ``version``, ``content_type``, ``created_at``) as last fetched."""

    def __init__(self, client: Client, info: dict):
        self.client = client
        self.info = info
        self.id = info["id"]
        # Positions known without asking, of the few versions used last.
        self._known = _Known()

    def __repr__(self):
        return (
            f"rayd.Scene({self.id[:12]}…, {self.info.get('triangles')} triangles, "
            f"version {self.info.get('version')})"
        )

    def __eq__(self, other):
        return isinstance(other, Scene) and other.id == self.id and other.client is self.client

    def __hash__(self):
        return hash(self.id)

    @property
    def _path(self):
        return f"/v1/scenes/{self.id}"

    def refresh(self) -> dict:
        """Fetches the summary again (``version`` moves with geometry updates)."""
        self.info = self.client._json("GET", self._path)
        # A new created_at is a new scene under the same id (deleted, uploaded again):
        # the positions known of the old one's versions are not this one's.
        self._known.keep_generation(self.info.get("created_at"))
        return self.info

    @property
    def version(self) -> int:
        """The latest geometry version, as the server says now."""
        return self.refresh()["version"]

    def delete(self) -> None:
        """Deletes the scene and every version of it."""
        self.client.delete(self)

    # -- geometry -------------------------------------------------------------------------

    def triangles(self, version: int | None = None, time: float | None = None) -> np.ndarray:
        """The world-space triangles traced at ``version`` (default: the latest) and
        ``time`` (version 1 only): ``(T, 3, 3)`` float32, rows ``v0, v1, v2``, in id order.

        Fetched from ``GET /v1/scenes/{id}/geometry`` (TRI1) and kept for the
        :data:`CACHED_VERSIONS` versions used last; positions this object uploaded are
        known without asking. Kept positions of a version after the first are answered
        only after the scene's summary shows it is still the scene they were fetched
        from (one small ``GET``), since a scene deleted and uploaded again has the same
        id and versions that count from 1 again."""
        fresh = version is None
        if fresh:
            version = self.version
        return self._entry(version, time, fresh)["triangles"]

    def _key(self, version, time):
        """The :class:`_Known` key of ``version``/``time`` in the generation last seen."""
        generation = None if version == 1 else self.info.get("created_at")
        return (generation, version, None if time is None else float(time))

    def _entry(self, version, time, fresh: bool) -> dict:
        """The known positions of ``version``/``time``, fetched when not known. ``fresh``:
        the summary was fetched just now, so its generation is the server's."""
        t = None if time is None else float(time)
        if version != 1 and not fresh and self._known.holds(version, t):
            self.refresh()  # which scene the server has under this id now
        # The generation is the one seen before the positions are asked for: if the
        # scene is made again in between, they are filed under one never seen again.
        key = self._key(version, t)
        entry = self._known.get(key)
        if entry is None:
            _, body = self.client._binary(
                "GET", f"{self._path}/geometry", params={"version": version, "time": time}
            )
            tris = formats.decode_triangles(body)
            if tris.shape[0] != self.info.get("triangles", tris.shape[0]):
                raise FormatError(
                    f"TRI1: {tris.shape[0]} triangles answered for a scene of "
                    f"{self.info['triangles']}"
                )
            entry = self._known.put(key, tris)
        return entry

    def _normals(self, version, time, fresh: bool = False) -> np.ndarray:
        """Unit face normals of every triangle at ``version``/``time``, plus a zero row."""
        entry = self._entry(version, time, fresh)
        if "normals" not in entry:
            n = triangle_normals(entry["triangles"])
            entry["normals"] = np.concatenate([n, np.zeros((1, 3), np.float32)])
        return entry["normals"]

    def _remember(self, version, time, triangles) -> None:
        """Keeps ``triangles`` as the positions of ``version``/``time``."""
        self._known.put(self._key(version, time), triangles)

    def update_geometry(self, triangles) -> int:
        """New positions for every triangle (``(T, 3, 3)`` or ``(T, 9)``, same ids): a new
        version, returned. Traces default to the latest version from then on."""
        body = formats.encode_triangles(triangles)
        generation = self.info.get("created_at")  # seen before the version is made
        # Never sent twice: a PUT that arrived made a version, and a second makes another.
        answer = self.client._json(
            "PUT", f"{self._path}/geometry", data=body, headers={"Content-Type": TRI_MEDIA}
        )
        return self._made_version(int(answer["version"]), body, generation)

    def _made_version(self, version: int, tri1, generation) -> int:
        """Notes ``version``, made from the TRI1 bytes ``tri1`` in the scene of
        ``generation`` (its ``created_at`` before the request): the latest, and known."""
        self.info["version"] = version
        known = formats.decode_triangles(tri1)
        known.flags.writeable = False
        self._known.put((generation, version, None), known)
        return version

    # -- tracing --------------------------------------------------------------------------

    @staticmethod
    def _trace_params(query, hit, accel, version, time, build, precision, invalid):
        if hit not in HIT_FORMATS:
            raise ValueError(f"hit must be one of {', '.join(HIT_FORMATS)}, not {hit!r}")
        return {
            "query": query,
            "hit": hit,
            "accel": accel,
            "version": version,
            "time": None if time is None else repr(float(time)),
            "build": build,
            "precision": precision,
            "invalid": invalid,
        }

    def trace(
        self,
        origins,
        directions,
        tmin=0.0,
        tmax=np.inf,
        query: str = "closest",
        hit: str = "t_prim_uv",
        accel: str | None = None,
        version: int | None = None,
        time: float | None = None,
        *,
        build: str | None = None,
        precision: str | None = None,
        invalid: str | None = None,
    ) -> Hits:
        """Traces rays ``origins + t·directions`` for ``tmin <= t <= tmax``.

        ``origins``/``directions`` are ``(N, 3)`` (or one ``(3,)`` for all); ``tmin``/``tmax``
        scalars or ``(N,)``. ``query`` is ``closest`` or ``any``; ``hit`` chooses the fields
        (``t_prim_uv``, ``t_prim``, ``t``, ``occluded``); ``accel``, ``build``,
        ``precision``, ``version``, ``time`` and ``invalid`` (``error`` or ``miss``) are the
        trace route's parameters, the server's defaults when None. Returns :class:`Hits`.
        """
        params = self._trace_params(query, hit, accel, version, time, build, precision, invalid)
        # Encoded a segment at a time as it is sent, so that the server's tracing of the
        # first segments overlaps the encoding of the rest (formats.RaySegments).
        body = formats.RaySegments(origins, directions, tmin, tmax)
        return self._trace_body(body, body.count, params)

    def trace_ray1(self, body, *, hit: str = "t_prim_uv", **params) -> Hits:
        """Traces a ready RAY1 body (bytes of a ``.ray`` file) as it is; ``params`` as
        :meth:`trace`'s keywords."""
        n = formats.decode_rays(body).shape[0]
        full = self._trace_params(
            params.pop("query", "closest"),
            hit,
            *(params.pop(k, None) for k in
              ("accel", "version", "time", "build", "precision", "invalid")),
        )
        if params:
            raise TypeError(f"unknown trace parameters: {', '.join(params)}")
        return self._trace_body(body, n, full)

    def _trace_body(self, body, n, params, route="trace", media=OCTET) -> Hits:
        """POSTs ``body`` (``n`` rays, after whatever else ``route`` takes) to ``route``
        and reads the HIT1 answer."""
        resp, answer = self.client._binary(
            "POST", f"{self._path}/{route}", params=params, data=body,
            headers={"Content-Type": media},
            # A trace changes nothing and may be sent again; a frame makes a version.
            replay=route == "trace",
        )
        records = formats.decode_hits(answer, HIT_FORMATS[params["hit"]], n)
        version = resp.headers.get("X-Rayd-Version")
        return Hits(
            answer,
            records,
            accel=resp.headers.get("X-Rayd-Accel"),
            server_timing=_server_timing(resp.headers.get("Server-Timing")),
            version=None if version is None else int(version),
        )

    def frame(
        self,
        triangles,
        origins,
        directions,
        tmin=0.0,
        tmax=np.inf,
        query: str = "closest",
        hit: str = "t_prim_uv",
        accel: str | None = None,
        *,
        build: str | None = None,
        precision: str | None = None,
        invalid: str | None = None,
    ) -> Hits:
        """New positions for every triangle and a trace against them, in one request
        (``POST …/frame``): what :meth:`update_geometry` then :meth:`trace` do, with one
        round trip. The new version is ``hits.version`` (and this scene's
        :attr:`version`); a frame refused for its positions makes none, one refused for
        its rays has made it (the problem's ``version``). Arguments as
        :meth:`update_geometry`'s and :meth:`trace`'s."""
        # (`version` and `time` stay None, which requests leaves out of the query.)
        params = self._trace_params(query, hit, accel, None, None, build, precision, invalid)
        tri = formats.encode_triangles(triangles)
        rays = formats.encode_rays(origins, directions, tmin, tmax)
        generation = self.info.get("created_at")  # seen before the version is made
        try:
            hits = self._trace_body(
                tri + rays, (len(rays) - 16) // 32, params, "frame", FRAME_MEDIA)
        except ProblemError as e:
            # Refused for its rays: the positions are a version all the same.
            if isinstance(e.extras.get("version"), int):
                self._made_version(e.extras["version"], tri, generation)
            raise
        self._made_version(hits.version, tri, generation)
        return hits

    def trace_async(self, origins, directions, tmin=0.0, tmax=np.inf, *,
                    idempotency_key: str | None = None, **kw) -> Job:
        """:meth:`trace` as a job (``Prefer: respond-async``); ``Job.result()`` gives the
        :class:`Hits`. With ``idempotency_key``, a retry of the same rays finds the first
        job (the same key with other rays is a 409)."""
        params = self._trace_params(
            kw.pop("query", "closest"),
            kw.pop("hit", "t_prim_uv"),
            *(kw.pop(k, None) for k in
              ("accel", "version", "time", "build", "precision", "invalid")),
        )
        if kw:
            raise TypeError(f"unknown trace parameters: {', '.join(kw)}")
        body = formats.encode_rays(origins, directions, tmin, tmax)
        headers = {"Content-Type": OCTET, "Prefer": "respond-async"}
        if idempotency_key:
            headers["Idempotency-Key"] = idempotency_key
        info = self.client._json(
            "POST", f"{self._path}/trace", params=params, data=body, headers=headers,
            replay=bool(idempotency_key),  # without a key, a second POST is a second job
        )
        return Job(self.client, info, expect=(HIT_FORMATS[params["hit"]],
                                              (len(body) - 16) // 32))

    def cast_rays(self, rays, *, accel=None, version=None, time=None, precision=None,
                  invalid: str | None = None, tmin=0.0, tmax=np.inf) -> dict:
        """Open3D's ``RaycastingScene.cast_rays`` against this scene.

        ``rays`` is ``(..., 6)``: origin and direction (any leading shape, float32 or
        convertible; an Open3D tensor works too). Every ray spans ``0 <= t < inf`` in units
        of its direction's length. Returns Open3D's keys, dtypes and miss values, shaped
        like ``rays[..., 0]``: ``t_hit`` (float32, inf), ``geometry_ids`` (uint32, 0 for
        this scene's one geometry, 4294967295 = INVALID_ID), ``primitive_ids`` (uint32,
        INVALID_ID), ``primitive_uvs`` (float32 ``(..., 2)``, 0) and
        ``primitive_normals`` (float32 ``(..., 3)``, unit geometric normals
        ``(v1-v0) × (v2-v0)`` as Embree reports them, not turned to the ray; 0).
        Normals are computed here from the triangles of the version traced
        (:meth:`triangles`). ``accel``, ``version``, ``time`` and ``precision`` are
        :meth:`trace`'s.

        Beyond Open3D's: ``invalid="miss"`` answers rays with a NaN or infinite coordinate
        or a zero direction (a depth camera's holes) as misses instead of refusing the
        batch (422; ``"error"``, the default), as :meth:`trace`'s ``invalid``; ``tmin`` and
        ``tmax`` (scalars, or shaped like ``rays[..., 0]``) narrow the interval, so that
        ``cast_rays(rays.as_open3d(), tmax=rays["tmax"])`` keeps the ``tmax`` given to
        :func:`rayd.spawn_rays`, which Open3D's layout cannot hold."""
        if hasattr(rays, "numpy") and not isinstance(rays, np.ndarray):
            rays = rays.numpy()
        r = np.asarray(rays, dtype=np.float32)
        if r.ndim < 1 or r.shape[-1] != 6:
            raise ValueError(f"rays must have shape (..., 6), not {r.shape}")
        lead = r.shape[:-1]
        flat = r.reshape(-1, 6)
        lo, hi = (np.broadcast_to(np.asarray(x, np.float32), lead).reshape(-1)
                  if np.ndim(x) else x for x in (tmin, tmax))
        if version is None:
            version = self.version  # pinned, so the normals are those of the version traced
        hits = self.trace(flat[:, :3], flat[:, 3:], lo, hi, accel=accel,
                          version=version, time=time, precision=precision, invalid=invalid)
        # Asked after the trace, so that normals known from before it answer only when
        # the summary shows the same scene (see triangles()).
        return open3d_answer(hits.records, self._normals(version, time), lead, version)

    # -- rendering ------------------------------------------------------------------------

    def render(self, *, idempotency_key: str | None = None, **options) -> Job:
        """Starts a render job with the options of ``rayd render`` (``width``, ``height``,
        ``spp``, ``integrator``, ``bounces``, ``camera`` or ``eye``/``target``/``up``,
        ``fov``, ``format``, ``accel``, ``time``, ``version``, ``seed``, ``frames``,
        ``priority``, ``callback``, ...; ``proto/openapi.yaml``, ``RenderRequest``). Options left None
        take the server's defaults. Returns the :class:`Job`."""
        body = {k: _plain(v) for k, v in options.items() if v is not None}
        headers = {"Idempotency-Key": idempotency_key} if idempotency_key else None
        info = self.client._json("POST", f"{self._path}/render", json_body=body,
                                 headers=headers, replay=bool(idempotency_key))
        return Job(self.client, info)


def _plain(v):
    """numpy values as JSON ones."""
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    return v


class Job:
    """A render or asynchronous trace on the server; ``info`` is its record as last seen
    (``state``, ``progress``, ``stats``, ``error``, ``results``, ...)."""

    def __init__(self, client: Client, info: dict, *, expect=None):
        self.client = client
        self.info = info
        self.id = info["id"]
        self._expect = expect
        # The last result fetched: (frame, ETag, Content-Type, bytes). Asking for it again
        # sends its ETag, and a 304 answer reuses these bytes instead of downloading them.
        self._last_result = None

    def __repr__(self):
        return f"rayd.Job({self.id}, {self.info.get('kind')}, {self.info.get('state')})"

    @property
    def _path(self):
        return f"/v1/jobs/{self.id}"

    @property
    def state(self) -> str:
        """The state as last seen (``refresh()`` asks again)."""
        return self.info["state"]

    def refresh(self) -> dict:
        """Fetches the job's record."""
        self.info = self.client._json("GET", self._path)
        return self.info

    def _events(self, deadline):
        """Job records from the SSE stream, each as it arrives, until the stream ends.

        A stream that cannot be opened, breaks off (the server going away) or stays
        silent until the deadline just ends: :meth:`wait` polls after it, and decides
        there whether the deadline has passed."""
        # The server sends a keep-alive comment every 15 s: a stream silent for twice that
        # (or the client's timeout, if longer) is a server that hangs, and ends here.
        silent = max(self.client.timeout or 0, 2 * _KEEP_ALIVE_SECONDS)
        read_timeout = silent if deadline is None else max(
            min(deadline - _time.monotonic(), silent), 0.1)
        try:
            resp = self.client._request(
                "GET", f"{self._path}/events", stream=True,
                headers={"Accept": "text/event-stream"},
                # Connecting counts against the deadline too: a server whose listen queue
                # is full hangs the connect, not the read.
                timeout=(self.client.timeout if deadline is None
                         else min(self.client.timeout, read_timeout), read_timeout),
                # A 503 (busy, starting) is ridden out by polling, within the deadline.
                retry=False,
            )
        except (requests.ConnectionError, requests.Timeout):
            return
        except ProblemError as e:
            if e.status == 503:
                return
            raise
        try:
            buf = b""
            data = []
            event = "message"
            # A read timeout inside iter_content comes as a ConnectionError (requests
            # wraps urllib3's ReadTimeoutError), a connection cut mid-body as a
            # ChunkedEncodingError: both end the stream.
            for chunk in resp.iter_content(chunk_size=None):
                buf += chunk
                *lines, buf = buf.split(b"\n")
                for raw in lines:
                    line = raw.rstrip(b"\r").decode("utf-8")
                    if not line:  # An empty line ends one event.
                        if data and event == "job":
                            yield json.loads("\n".join(data))
                        data, event = [], "message"
                        continue
                    if line.startswith(":"):
                        continue  # A comment: the server's keep-alive.
                    field, _, value = line.partition(":")
                    value = value[1:] if value.startswith(" ") else value
                    if field == "data":
                        data.append(value)
                    elif field == "event":
                        event = value
                if deadline is not None and _time.monotonic() > deadline:
                    return
        except (requests.ConnectionError, requests.Timeout,
                requests.exceptions.ChunkedEncodingError):
            return
        finally:
            resp.close()

    def _poll(self, deadline):
        """The job's record, asked for again and again (with a growing pause) while the
        server cannot be reached, answers 503 or is slow: until the deadline, or without
        one for the client's ``timeout`` seconds of failures in a row (a server restarting
        takes a few seconds; one that is gone should not be waited for forever). None
        once the deadline has passed."""
        pause = 0.05
        failing_since = None
        while True:
            now = _time.monotonic()
            if deadline is not None and now > deadline:
                return None
            limit = self.client.timeout
            if deadline is not None:
                limit = max(min(limit, deadline - now), 0.1)
            try:
                return self.client._json("GET", self._path, timeout=limit)
            except (requests.ConnectionError, requests.Timeout, ProblemError) as e:
                if isinstance(e, ProblemError) and e.status != 503:
                    raise
                failing_since = now if failing_since is None else failing_since
                if deadline is None and _time.monotonic() - failing_since > self.client.timeout:
                    raise
            wait = pause if deadline is None else min(pause, max(deadline - _time.monotonic(), 0))
            _time.sleep(wait)
            pause = min(pause * 2, 1.0)

    def wait(self, progress: bool = True, timeout: float | None = None, check: bool = True) -> Job:
        """Waits for the job to end, following its event stream; with ``progress`` a tqdm
        bar shows its progress. Returns the job itself (so ``job.wait().result()`` reads
        well), its final record in :attr:`info`; a job that failed or was cancelled raises
        :class:`rayd.JobError` unless ``check`` is False. ``timeout`` (seconds) raises
        ``TimeoutError`` when the job has not ended by then. A server that goes away during
        the wait (a restart) is asked again until the deadline, or without one for the
        client's ``timeout`` seconds, so a wait outlives a restart."""
        deadline = None if timeout is None else _time.monotonic() + timeout
        bar = None
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=100, desc=f"{self.info.get('kind', 'job')} {self.id[:8]}",
                       unit="%", bar_format="{l_bar}{bar}| {n:.0f}% [{elapsed}<{remaining}{postfix}]")

        def show(info):
            self.info = info
            if bar is not None:
                bar.n = round(100 * float(info.get("progress") or 0))
                bar.set_postfix_str(info.get("state", ""), refresh=False)
                bar.refresh()

        try:
            if self.info.get("state") not in _FINAL:
                for info in self._events(deadline):
                    show(info)
                    if info.get("state") in _FINAL:
                        break
            # A stream that closed early (the server shutting down or restarting, a
            # proxy's timeout) or stayed silent: poll until the end or the deadline,
            # through a server that is restarting.
            pause = 0.05
            while self.info.get("state") not in _FINAL:
                if deadline is not None and _time.monotonic() > deadline:
                    raise TimeoutError(
                        f"job {self.id} is still {self.info.get('state')} after {timeout} s"
                    )
                _time.sleep(pause if deadline is None
                            else min(pause, max(deadline - _time.monotonic(), 0)))
                pause = min(pause * 2, 1.0)
                info = self._poll(deadline)
                if info is not None:
                    show(info)
            show(self.info)
        finally:
            if bar is not None:
                bar.close()
        if check and self.info["state"] != "succeeded":
            raise JobError(self.info)
        return self

    def result(self, *, raw: bool = False, frame: int | None = None):
        """The finished job's result (409 ``ProblemError`` while it runs).

        A render's PNG comes back as an ``(H, W, C)`` uint8 array when Pillow is installed,
        else as the PNG's bytes; an EXR always as bytes; an asynchronous trace's HIT1 as
        :class:`Hits`. ``raw=True`` gives the bytes in every case. ``frame`` picks one frame
        of a multi-frame render. Asking again for the result last fetched sends its
        ``ETag`` as ``If-None-Match``: the server answers 304 and the bytes are not sent
        again."""
        kept = self._last_result if self._last_result and self._last_result[0] == frame else None
        headers = {"If-None-Match": kept[1]} if kept else None
        resp, body = self.client._binary("GET", f"{self._path}/result", params={"frame": frame},
                                         headers=headers)
        if resp.status_code == 304 and kept:
            ctype, body = kept[2], kept[3]
        else:
            ctype = resp.headers.get("Content-Type", "").split(";")[0].strip()
            etag = resp.headers.get("ETag")
            self._last_result = (frame, etag, ctype, body) if etag else None
        if raw:
            return body
        if ctype == OCTET:
            fmt, count = self._expect if self._expect else (None, None)
            return Hits(body, formats.decode_hits(body, fmt, count))
        if ctype == "image/png":
            try:
                from PIL import Image
            except ImportError:
                return body
            with Image.open(io.BytesIO(body)) as img:
                return np.asarray(img)
        return body

    def cancel(self) -> dict | None:
        """Cancels a queued or running job (its record, now ``cancelled``, is returned), or
        deletes an ended one with its result (None)."""
        resp = self.client._request("DELETE", self._path)
        if resp.status_code == 204:
            return None
        self.info = resp.json()
        return self.info
