"""RAY1, HIT1 and TRI1 (the repository's ``proto/binary-formats.md``) as numpy dtypes.

Every body is a 16-byte header and then fixed-size records, so a numpy structured dtype
with the same layout reads a body with ``np.frombuffer`` (no per-ray Python loop, no copy)
and writes one by filling a view over a preallocated ``bytearray`` (the only copy: from the
caller's arrays into the wire buffer). Readers check what the server's readers check, in the
same order, so a broken body fails here with a message that says which rule and where.
"""

from __future__ import annotations

import struct
import sys

import numpy as np

from .errors import FormatError

HEADER = struct.Struct("<IHHQ")
"""``magic: u32, version: u16, format: u16, count: u64``, little-endian."""
HEADER_BYTES = HEADER.size

RAY1_MAGIC = 0x31594152
HIT1_MAGIC = 0x31544948
TRI1_MAGIC = 0x31495254
VERSION = 1

RAY_DTYPE = np.dtype(
    [
        ("origin", "<f4", (3,)),
        ("tmin", "<f4"),
        ("direction", "<f4", (3,)),
        ("tmax", "<f4"),
    ]
)
"""One RAY1 record: OptiX Prime's ORIGIN_TMIN_DIRECTION_TMAX, 32 bytes."""

TRI_DTYPE = np.dtype(("<f4", (3, 3)))
"""One TRI1 record: ``v0, v1, v2`` as 9 f32, 36 bytes."""

HIT_FORMATS = {"t_prim_uv": 0, "t_prim": 1, "t": 2, "occluded": 3}
"""The ``hit=`` names and their HIT1 format codes."""

HIT_DTYPES = {
    0: np.dtype([("t", "<f4"), ("prim", "<u4"), ("u", "<f4"), ("v", "<f4")]),
    1: np.dtype([("t", "<f4"), ("prim", "<u4")]),
    2: np.dtype([("t", "<f4")]),
    3: np.dtype([("occluded", "u1")]),
}
"""The record of each HIT1 format (16, 8, 4 and 1 bytes)."""

MISS_PRIM = 0xFFFFFFFF
"""``prim`` of a miss (and Open3D's ``RaycastingScene.INVALID_ID``)."""

_KINDS = {RAY1_MAGIC: "RAY1", HIT1_MAGIC: "HIT1", TRI1_MAGIC: "TRI1"}


def header(magic: int, fmt: int, count: int) -> bytes:
    """The 16-byte header of a body of ``count`` records."""
    return HEADER.pack(magic, VERSION, fmt, count)


def _check(body, magic: int, record_bytes_of, kind: str) -> tuple[int, int]:
    """Checks a body's header and length; returns ``(format, count)``."""
    n = len(body)
    if n < HEADER_BYTES:
        raise FormatError(f"{kind}: body is {n} bytes, shorter than the 16-byte header")
    got_magic, version, fmt, count = HEADER.unpack_from(body, 0)
    if got_magic != magic:
        found = _KINDS.get(got_magic, f"0x{got_magic:08X}")
        raise FormatError(f"{kind}: magic at byte 0 is {found}, not {kind}")
    if version != VERSION:
        raise FormatError(f"{kind}: version at byte 4 is {version}, not 1")
    record = record_bytes_of(fmt)
    if record is None:
        raise FormatError(f"{kind}: format at byte 6 is {fmt}, not one of {kind}'s")
    need = HEADER_BYTES + count * record  # Python ints: no overflow.
    if n != need:
        raise FormatError(
            f"{kind}: body is {n} bytes but its header's count {count} needs {need}"
        )
    return fmt, count


def _numbers(a):
    """``a`` as an array of real numbers: a float32 or other numeric array stays as it is
    (converted to float32 a segment at a time while it is written, not all at once);
    anything else is converted now, which raises for what is not numbers."""
    a = np.asarray(a)
    if a.dtype.kind in "fiub" and a.dtype.itemsize <= 8:
        return a
    return np.asarray(a, dtype=np.float32)


def _ray_arrays(origins, directions, tmin, tmax):
    """The four inputs as numeric arrays, checked, and the ray count. One ray's worth
    (``(1, 3)`` or ``(1,)``) is kept as one value for all rays."""
    o, d, lo, hi = (_numbers(a) for a in (origins, directions, tmin, tmax))
    for name, a, rank in (("origins", o, 2), ("directions", d, 2)):
        if a.ndim not in (1, rank) or a.shape[-1] != 3:
            raise ValueError(f"{name} must have shape (N, 3) or (3,), not {a.shape}")
    for name, a in (("tmin", lo), ("tmax", hi)):
        if a.ndim > 1:
            raise ValueError(f"{name} must be a scalar or have shape (N,), not {a.shape}")
    try:
        count = np.broadcast_shapes(o.shape[:-1], d.shape[:-1], lo.shape, hi.shape)
    except ValueError:
        raise ValueError(
            f"ray counts disagree: origins {o.shape}, directions {d.shape}, "
            f"tmin {lo.shape}, tmax {hi.shape}"
        ) from None
    n = count[0] if count else 1
    # A leading axis of length 1 broadcasts: keep its one value, so that slicing rays
    # start..stop never empties it.
    o, d = (a[0] if a.ndim == 2 and a.shape[0] == 1 else a for a in (o, d))
    lo, hi = (a.reshape(()) if a.ndim == 1 and a.shape[0] == 1 else a for a in (lo, hi))
    return o, d, lo, hi, n


_RAY_ROWS = np.dtype(
    {
        "names": ["origin", "tmin", "direction", "tmax"],
        "formats": ["V12", "<f4", "V12", "<f4"],
        "offsets": [0, 12, 16, 28],
        "itemsize": RAY_DTYPE.itemsize,
    }
)
"""RAY_DTYPE with each vector as one opaque 12-byte value: numpy copies an ``(N, 3)``
float32 array into it as ``N`` 12-byte moves instead of ``3 N`` strided element copies,
which halves the client's encoding time (BENCHMARKS §15)."""

_LITTLE = sys.byteorder == "little"

SEGMENT = 1 << 16
"""Rays converted and written at a time by :func:`encode_rays` and :class:`RaySegments`:
a float64 input is converted a segment at a time, never as a whole second copy."""


def _rows(a):
    """``a``, an ``(N, 3)`` array, as ``N`` 12-byte values viewing it, or None where a
    row's bytes are not the wire's (not three adjacent float32, or a big-endian machine).
    Rows need not be adjacent: the origin and direction halves of an ``(N, 6)`` array
    (``cast_rays``) are 12-byte values 24 bytes apart."""
    if _LITTLE and a.ndim == 2 and a.dtype == np.float32 and a.strides[1] == 4:
        try:
            return a.view("V12").reshape(-1)
        except ValueError:  # numpy < 1.23 views only contiguous arrays as another size
            return None
    return None


def _fill_rays(rec, o, d, lo, hi, start, stop):
    """Writes rays ``start..stop`` of the inputs (broadcast) into the records ``rec``."""

    def part(a, vector):
        # One value (or vector) for all rays stays as it is and broadcasts.
        return a[start:stop] if a.ndim == (2 if vector else 1) else a

    rows = rec.view(_RAY_ROWS)
    for name, a in (("origin", o), ("direction", d)):
        a = part(a, True)
        if a.ndim == 2 and a.dtype != np.float32:
            a = a.astype(np.float32)  # this segment's rows only, while they are in cache
        packed = _rows(a)
        if packed is not None:
            rows[name] = packed
        else:
            rec[name] = a
    rec["tmin"] = part(lo, False)
    rec["tmax"] = part(hi, False)


def encode_rays(origins, directions, tmin=0.0, tmax=np.inf) -> bytearray:
    """A RAY1 body for rays ``origins + t * directions``, ``tmin <= t <= tmax``.

    ``origins`` and ``directions`` are ``(N, 3)`` (either may be one ``(3,)`` point or vector
    for all rays); ``tmin`` and ``tmax`` are scalars or ``(N,)``. Values are converted to
    float32 as they are written into the body, which is the one copy made.
    """
    o, d, lo, hi, n = _ray_arrays(origins, directions, tmin, tmax)
    body = bytearray(HEADER_BYTES + n * RAY_DTYPE.itemsize)
    HEADER.pack_into(body, 0, RAY1_MAGIC, VERSION, 0, n)
    rec = np.frombuffer(body, dtype=RAY_DTYPE, count=n, offset=HEADER_BYTES)
    for start in range(0, n, SEGMENT):
        stop = min(start + SEGMENT, n)
        _fill_rays(rec[start:stop], o, d, lo, hi, start, stop)
    return body


class RaySegments:
    """A RAY1 body encoded a segment at a time while it is sent: iterating gives the
    header and then the records of ``segment`` rays at a time, each written into one
    reused buffer just before it goes out, and ``len()`` is the whole body's length (so
    an HTTP library sends it with a ``Content-Length``, not chunked).

    The service traces a streamed batch as its segments arrive (``proto/service.md``), so
    encoding the next segment here overlaps tracing the last one there, instead of the
    whole body being encoded before its first byte leaves. The inputs are checked when
    this is made, before anything is sent; iterating again encodes the body again (a
    retried request).
    """

    def __init__(self, origins, directions, tmin=0.0, tmax=np.inf, segment: int = SEGMENT):
        self._o, self._d, self._lo, self._hi, self.count = _ray_arrays(
            origins, directions, tmin, tmax
        )
        self._segment = max(int(segment), 1)

    def __len__(self):
        return HEADER_BYTES + self.count * RAY_DTYPE.itemsize

    def __iter__(self):
        yield header(RAY1_MAGIC, 0, self.count)
        rec = np.empty(min(self._segment, self.count), dtype=RAY_DTYPE)
        for start in range(0, self.count, self._segment):
            stop = min(start + self._segment, self.count)
            part = rec[: stop - start]
            _fill_rays(part, self._o, self._d, self._lo, self._hi, start, stop)
            # The socket has taken these bytes when the next segment overwrites them.
            yield memoryview(part).cast("B")


def decode_rays(body) -> np.ndarray:
    """The records of a RAY1 body as a RAY_DTYPE array viewing ``body``."""
    _, count = _check(body, RAY1_MAGIC, lambda f: 32 if f == 0 else None, "RAY1")
    return np.frombuffer(body, dtype=RAY_DTYPE, count=count, offset=HEADER_BYTES)


def encode_triangles(triangles) -> bytearray:
    """A TRI1 body for ``(T, 3, 3)`` triangles (or ``(T, 9)``), rows ``v0, v1, v2``."""
    a = np.asarray(triangles, dtype=np.float32)
    if a.ndim == 2 and a.shape[1] == 9:
        a = a.reshape(-1, 3, 3)
    if a.ndim != 3 or a.shape[1:] != (3, 3):
        raise ValueError(f"triangles must have shape (T, 3, 3) or (T, 9), not {a.shape}")
    bad = ~np.isfinite(a).all(axis=(1, 2))
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"triangle {i} has a NaN or infinite coordinate: {a[i].tolist()}")
    t = a.shape[0]
    body = bytearray(HEADER_BYTES + t * TRI_DTYPE.itemsize)
    HEADER.pack_into(body, 0, TRI1_MAGIC, VERSION, 0, t)
    np.frombuffer(body, dtype=np.float32, offset=HEADER_BYTES).reshape(t, 3, 3)[...] = a
    return body


def decode_triangles(body) -> np.ndarray:
    """The triangles of a TRI1 body as a ``(T, 3, 3)`` float32 array viewing ``body``."""
    _, count = _check(body, TRI1_MAGIC, lambda f: 36 if f == 0 else None, "TRI1")
    return np.frombuffer(body, dtype="<f4", count=count * 9, offset=HEADER_BYTES).reshape(
        count, 3, 3
    )


def decode_hits(body, expect_format: int | None = None, expect_count: int | None = None):
    """The records of a HIT1 body as a structured array viewing ``body``.

    With ``expect_format`` or ``expect_count``, an answer that is not what was asked for
    (another format, another number of records) is a :class:`FormatError` too.
    """

    def size(f):
        return HIT_DTYPES[f].itemsize if f in HIT_DTYPES else None

    fmt, count = _check(body, HIT1_MAGIC, size, "HIT1")
    if expect_format is not None and fmt != expect_format:
        raise FormatError(f"HIT1: format {fmt} answered where {expect_format} was asked for")
    if expect_count is not None and count != expect_count:
        raise FormatError(f"HIT1: {count} records answered for {expect_count} rays")
    return np.frombuffer(body, dtype=HIT_DTYPES[fmt], count=count, offset=HEADER_BYTES)


def hit_arrays(records: np.ndarray) -> dict:
    """The fields of HIT1 records as a dict of arrays (views; ``occluded`` as bool)."""
    out = {}
    for name in records.dtype.names:
        out[name] = records[name].view(np.bool_) if name == "occluded" else records[name]
    return out
