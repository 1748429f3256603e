"""A Python client for ``rayd serve``: numpy arrays of rays in, numpy arrays of hits out.

>>> import rayd
>>> client = rayd.Client("http://127.0.0.1:8080")
>>> scene = client.upload("scenes/Fox.glb")
>>> hits = scene.trace(origins, directions)          # {"t", "prim", "u", "v"}
>>> ans = scene.cast_rays(rays)                      # Open3D's RaycastingScene.cast_rays
>>> image = scene.render(width=320, height=240).wait().result()  # doctest: +SKIP

The wire formats are the repository's ``proto/binary-formats.md`` (:mod:`rayd.formats`),
the routes ``proto/openapi.yaml``.
"""

from .client import Client, Hits, Job, Scene
from .errors import FormatError, JobError, ProblemError, RaydError
from .formats import MISS_PRIM
from .spawn import Rays, face_normals, hit_points, offset_ray, spawn_rays, triangle_normals

INVALID_ID = MISS_PRIM
"""Open3D's ``RaycastingScene.INVALID_ID``: the id of a miss (0xFFFFFFFF)."""

__version__ = "0.1.0"

__all__ = [
    "Client",
    "FormatError",
    "Hits",
    "INVALID_ID",
    "Job",
    "JobError",
    "MISS_PRIM",
    "ProblemError",
    "Rays",
    "RaydError",
    "Scene",
    "face_normals",
    "hit_points",
    "offset_ray",
    "spawn_rays",
    "triangle_normals",
]
