"""Schemathesis hooks for rayd (loaded by scripts/schemathesis.sh via SCHEMATHESIS_HOOKS).

The document (proto/openapi.yaml) says the binary bodies are `format: binary`, which tells a
generator nothing; these strategies make bodies of each media type that are sometimes valid
(so the happy paths run: traces, uploads, geometry versions) and often broken in the ways a
client breaks them (wrong magic, short header, a count that disagrees with the length, NaN
components, truncated or mangled files), so the error paths run too.

Path parameters are steered to the scene and job the script made before the run (the
environment variables below), mixed with the generated values (ids that name nothing).
DELETE operations get a scene or job of their own, made here, so they do not remove the
shared ones.

A check replaces `not_a_server_error`: a 5xx fails unless it is a 503 with `Retry-After`
(the document's overload answer).

Environment: RAYD_URL (base URL), RAYD_SCENE (id of the uploaded scene), RAYD_SCENE_TRIANGLES
(its triangle count), RAYD_JOB (id of a finished render job).
"""

import json
import os
import struct
import urllib.request
from pathlib import Path

import schemathesis
from hypothesis import strategies as st

URL = os.environ.get("RAYD_URL", "http://127.0.0.1:8080")
SCENE = os.environ.get("RAYD_SCENE", "")
SCENE_TRIANGLES = int(os.environ.get("RAYD_SCENE_TRIANGLES", "1"))
JOB = os.environ.get("RAYD_JOB", "")
SCENES_DIR = Path(__file__).resolve().parent.parent / "scenes"

RAY1_MAGIC = 0x31594152
TRI1_MAGIC = 0x31495254

# Floats a client might send: ordinary ones and the special values the server must refuse
# (or, with invalid=miss, answer as misses) without failing.
ordinary = st.floats(min_value=-10.0, max_value=10.0, allow_nan=False, width=32)
special = st.sampled_from([float("nan"), float("inf"), float("-inf"), 0.0, -0.0, 1e30])
component = st.one_of(ordinary, ordinary, ordinary, special)


def header(magic, version, fmt, count):
    """The 16-byte header shared by RAY1, HIT1 and TRI1 (proto/binary-formats.md)."""
    return struct.pack("<IHHQ", magic, version, fmt, count)


def mangle(valid):
    """Ways a valid body goes wrong on its way to the server."""
    return st.one_of(
        st.just(b""),
        valid.map(lambda b: b[: max(0, len(b) - 1)]),  # one byte short
        valid.map(lambda b: b[:10]),  # a short header
        valid.map(lambda b: b + b"\0"),  # one byte too many
        valid.map(lambda b: b"XXXX" + b[4:]),  # wrong magic
        valid.map(lambda b: b[:4] + struct.pack("<H", 7) + b[6:]),  # unknown version
        valid.map(lambda b: b[:6] + struct.pack("<H", 9) + b[8:]),  # unknown format
        valid.map(lambda b: b[:8] + struct.pack("<Q", 2**64 - 1) + b[16:]),  # huge count
        st.binary(max_size=256),
    )


@st.composite
def ray1_valid(draw):
    n = draw(st.integers(min_value=0, max_value=16))
    body = bytearray(header(RAY1_MAGIC, 1, 0, n))
    for _ in range(n):
        o = [draw(ordinary) for _ in range(3)]
        d = [draw(ordinary) for _ in range(3)]
        if not any(d):
            d[2] = -1.0
        tmin = draw(st.sampled_from([0.0, 1e-4]))
        tmax = draw(st.sampled_from([float("inf"), 1e3, 5.0]))
        body += struct.pack("<8f", *o, tmin, *d, tmax)
    return bytes(body)


@st.composite
def ray1_odd(draw):
    """Well-formed RAY1 whose rays may be invalid (NaN, zero direction, negative tmin)."""
    n = draw(st.integers(min_value=1, max_value=8))
    body = bytearray(header(RAY1_MAGIC, 1, 0, n))
    for _ in range(n):
        body += struct.pack("<8f", *[draw(component) for _ in range(8)])
    return bytes(body)


ray1 = st.one_of(ray1_valid(), ray1_valid(), ray1_odd(), mangle(ray1_valid()))


@st.composite
def tri1_valid(draw, count=None):
    n = count if count is not None else draw(st.integers(min_value=1, max_value=8))
    body = bytearray(header(TRI1_MAGIC, 1, 0, n))
    for _ in range(n):
        body += struct.pack("<9f", *[draw(ordinary) for _ in range(9)])
    return bytes(body)


@st.composite
def tri1_nonfinite(draw):
    n = draw(st.integers(min_value=1, max_value=4))
    body = bytearray(header(TRI1_MAGIC, 1, 0, n))
    for _ in range(n):
        body += struct.pack("<9f", *[draw(component) for _ in range(9)])
    return bytes(body)


# The scene's own count (a valid new geometry version), any count (a valid upload, or a
# count mismatch for a version), non-finite vertices, and broken bodies.
tri1 = st.one_of(
    tri1_valid(count=SCENE_TRIANGLES),
    tri1_valid(),
    tri1_nonfinite(),
    mangle(tri1_valid()),
)


def real_glbs():
    # Fox.glb is larger than the run's --max-body: it exercises the 413 path. The shared
    # scene's file is left out: uploading it again names the shared scene, which stateful
    # tests would then delete.
    files = sorted(f for f in SCENES_DIR.glob("*.glb") if f.name != "BoxAnimated.glb")
    return [f.read_bytes() for f in files]


GLBS = real_glbs()
glb_valid = st.sampled_from(GLBS) if GLBS else st.just(b"")


@st.composite
def glb_mangled(draw):
    b = bytearray(draw(glb_valid))
    if not b:
        return b"glTF"
    kind = draw(st.integers(min_value=0, max_value=3))
    if kind == 0:  # truncated
        return bytes(b[: draw(st.integers(min_value=0, max_value=len(b) - 1))])
    if kind == 1:  # a flipped byte somewhere
        i = draw(st.integers(min_value=0, max_value=len(b) - 1))
        b[i] ^= draw(st.integers(min_value=1, max_value=255))
        return bytes(b)
    if kind == 2:  # a wrong total length in the header
        b[8:12] = struct.pack("<I", draw(st.integers(min_value=0, max_value=2**32 - 1)))
        return bytes(b)
    return draw(st.binary(max_size=128))


glb = st.one_of(glb_valid, glb_mangled())


def gltf_json_doc(positions, uri=None):
    """A one-mesh glTF JSON document with its buffer embedded as a data: URI."""
    import base64

    data = struct.pack(f"<{len(positions)}f", *positions)
    doc = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "accessors": [
            {
                "bufferView": 0,
                "componentType": 5126,
                "count": len(positions) // 3,
                "type": "VEC3",
                "min": [min(positions[i::3]) for i in range(3)],
                "max": [max(positions[i::3]) for i in range(3)],
            }
        ],
        "bufferViews": [{"buffer": 0, "byteLength": len(data)}],
        "buffers": [
            {
                "byteLength": len(data),
                "uri": uri
                or "data:application/octet-stream;base64," + base64.b64encode(data).decode(),
            }
        ],
    }
    return json.dumps(doc).encode()


@st.composite
def gltf_valid(draw):
    tris = draw(st.integers(min_value=1, max_value=4))
    positions = [draw(ordinary) for _ in range(9 * tris)]
    return gltf_json_doc(positions)


gltf = st.one_of(
    gltf_valid(),
    gltf_valid(),
    st.just(gltf_json_doc([0.0] * 9, uri="external.bin")),  # buffers not embedded
    gltf_valid().map(lambda b: b[: len(b) // 2]),  # truncated JSON
    st.just(b'{"asset": {"version": "1.0"}}'),
    st.just(b"[]"),
    st.binary(max_size=64),
)

# A frame: positions for the shared scene (or not), then rays, valid or broken.
frame = st.one_of(
    st.tuples(tri1_valid(count=SCENE_TRIANGLES), ray1_valid()).map(lambda p: p[0] + p[1]),
    st.tuples(tri1_valid(count=SCENE_TRIANGLES), ray1).map(lambda p: p[0] + p[1]),
    st.tuples(tri1, ray1).map(lambda p: p[0] + p[1]),
    tri1,
)

schemathesis.openapi.media_type("application/octet-stream", ray1)
schemathesis.openapi.media_type("application/x-rayd-frame", frame)
schemathesis.openapi.media_type("application/x-rayd-tri", tri1)
schemathesis.openapi.media_type("model/gltf-binary", glb)
schemathesis.openapi.media_type("model/gltf+json", gltf)


def _request(method, path, body=None, content_type=None):
    req = urllib.request.Request(URL + path, data=body, method=method)
    if content_type:
        req.add_header("Content-Type", content_type)
    with urllib.request.urlopen(req, timeout=30) as resp:
        return json.loads(resp.read() or b"null")


def fresh_scene():
    """A scene made for one DELETE (a TRI1 triangle with random corners)."""
    corners = list(struct.unpack("<9f", os.urandom(36)))
    corners = [c if c == c and abs(c) < 1e6 else 0.5 for c in corners]
    body = header(TRI1_MAGIC, 1, 0, 1) + struct.pack("<9f", *corners)
    return _request("POST", "/v1/scenes", body, "application/x-rayd-tri")["id"]


def fresh_job():
    """A job made for one DELETE (a tiny render of the shared scene)."""
    spec = json.dumps({"width": 4, "height": 4}).encode()
    return _request("POST", f"/v1/scenes/{SCENE}/render", spec, "application/json")["id"]


@schemathesis.hook
def flatmap_path_parameters(context, path_parameters):
    op = context.operation
    params = dict(path_parameters or {})
    deleting = op.method.upper() == "DELETE"
    choices = [st.just(params)]
    if "id" in params and SCENE:
        real = SCENE
        if deleting:
            try:
                real = fresh_scene()
            except OSError:
                real = SCENE
        choices += [st.just({**params, "id": real})] * 3
    if "job" in params and JOB:
        real = JOB
        if deleting:
            try:
                real = fresh_job()
            except OSError:  # the queue is full (503): delete the shared job's id then
                real = JOB
        choices += [st.just({**params, "job": real})] * 3
    return st.one_of(*choices)


@schemathesis.check
def no_server_error_but_documented_503(ctx, response, case):
    """No 5xx, except 503 with Retry-After (queue full, budgets spent, shutting down)."""
    status = response.status_code
    if status < 500:
        return None
    if status == 503 and response.headers.get("retry-after"):
        return None
    raise AssertionError(
        f"{status} from {case.method} {case.formatted_path}: {response.text[:500]}"
    )


HIT1_MAGIC = 0x31544948
HIT_FORMATS = {"t_prim_uv": (0, 16), "t_prim": (1, 8), "t": (2, 4), "occluded": (3, 1)}


@schemathesis.check
def hit1_answers_every_ray(ctx, response, case):
    """A 200 HIT1 body of a trace is well-formed: the `hit` format asked for, one record
    per ray sent, and exactly 16 + count × record bytes (proto/binary-formats.md)."""
    if response.status_code != 200 or case.method.upper() != "POST":
        return None
    if not case.path.endswith(("/trace", "/frame")):
        return None
    body = response.content
    if len(body) < 16:
        raise AssertionError(f"HIT1 body of {len(body)} bytes, shorter than its header")
    magic, version, fmt, count = struct.unpack("<IHHQ", body[:16])
    hit = (case.query or {}).get("hit", "t_prim_uv")
    want_fmt, record = HIT_FORMATS.get(hit, (None, None))
    if magic != HIT1_MAGIC or version != 1 or fmt != want_fmt:
        raise AssertionError(f"HIT1 header magic={magic:#x} version={version} format={fmt}, asked hit={hit}")
    sent = case.body if isinstance(case.body, (bytes, bytearray)) else b""
    if case.path.endswith("/frame"):
        sent = sent[16 + 36 * SCENE_TRIANGLES :]  # the rays after the positions
    rays = struct.unpack("<Q", sent[8:16])[0] if len(sent) >= 16 else None
    if rays is not None and count != rays:
        raise AssertionError(f"HIT1 count {count} for {rays} rays")
    if len(body) != 16 + count * record:
        raise AssertionError(f"HIT1 body of {len(body)} bytes for {count} records of {record}")
    return None
