"""The client's exceptions: one for the server's problem documents, one for bad bodies.

The server answers every error as RFC 9457 ``application/problem+json``
(``proto/service.md``, "Errors"); :class:`ProblemError` keeps each of its members, the
standard ones as attributes and the extension members (``ray_index``, ``count``, ``field``,
``byte_offset``, ``limit``, ...) in :attr:`ProblemError.extras` and as attributes too, so a
caller can act on *where* a request went wrong without parsing the message.
"""

from __future__ import annotations

import json

_STANDARD = ("type", "title", "status", "detail", "instance")


class RaydError(Exception):
    """Every error this package raises on purpose."""


class FormatError(RaydError, ValueError):
    """A RAY1, HIT1 or TRI1 body that breaks ``proto/binary-formats.md``."""


class ProblemError(RaydError):
    """An error answer of the server, with the members of its problem document.

    ``status`` is the HTTP status, ``instance`` the request id (the server logs under it),
    ``extras`` every extension member; each extra is also an attribute (``e.ray_index``).
    ``retry_after`` is the ``Retry-After`` header's seconds for a 503, else None.
    """

    def __init__(
        self,
        status: int,
        title: str,
        detail: str,
        *,
        type: str = "about:blank",  # noqa: A002 - the RFC 9457 member's name
        instance: str | None = None,
        extras: dict | None = None,
        method: str = "",
        url: str = "",
        retry_after: float | None = None,
    ):
        self.status = status
        self.title = title
        self.detail = detail
        self.type = type
        self.instance = instance
        self.extras = dict(extras or {})
        self.method = method
        self.url = url
        self.retry_after = retry_after
        where = f" ({method} {url})" if method else ""
        super().__init__(f"{status} {title}: {detail}{where}")

    def __reduce__(self):
        # Exception pickling rebuilds an error from ``self.args`` (the message alone), which
        # this __init__ does not take: a ProblemError raised in a worker process
        # (concurrent.futures, multiprocessing) could not come back. Rebuild it from its
        # members instead, and restore whatever else was set on it (``__notes__``, ...).
        kwargs = {
            "type": self.type,
            "instance": self.instance,
            "extras": self.extras,
            "method": self.method,
            "url": self.url,
            "retry_after": self.retry_after,
        }
        return (_rebuild, (type(self), (self.status, self.title, self.detail), kwargs),
                dict(self.__dict__))

    def __getattr__(self, name):
        # Only reached for names that are not ordinary attributes: the extension members.
        extras = self.__dict__.get("extras", {})
        if name in extras:
            return extras[name]
        raise AttributeError(name)

    @classmethod
    def from_response(cls, resp) -> ProblemError:
        """The error a ``requests`` response with a 4xx/5xx status stands for.

        A body that is not a problem document (a proxy's HTML page, hyper's bare 431) still
        gives an error with the status, the reason phrase and the start of the body.
        """
        req = resp.request
        method = req.method if req is not None else ""
        url = req.url if req is not None else resp.url
        retry = resp.headers.get("Retry-After")
        try:
            retry_after = float(retry) if retry is not None else None
        except ValueError:
            retry_after = None
        doc = None
        ctype = resp.headers.get("Content-Type", "")
        if "json" in ctype:
            try:
                doc = json.loads(resp.content)
            except ValueError:
                doc = None
        if not isinstance(doc, dict):
            text = resp.content[:500].decode("utf-8", "replace").strip()
            return cls(
                resp.status_code,
                resp.reason or "error",
                text or "(no body)",
                method=method,
                url=url,
                retry_after=retry_after,
            )
        extras = {k: v for k, v in doc.items() if k not in _STANDARD}
        return cls(
            int(doc.get("status", resp.status_code)),
            str(doc.get("title", resp.reason or "error")),
            str(doc.get("detail", "")),
            type=str(doc.get("type", "about:blank")),
            instance=doc.get("instance"),
            extras=extras,
            method=method,
            url=url,
            retry_after=retry_after,
        )


class JobError(RaydError):
    """A job that ended without succeeding (``failed`` or ``cancelled``); ``job`` is its record."""

    def __init__(self, job: dict):
        self.job = job
        state = job.get("state")
        why = job.get("error") or state
        super().__init__(f"job {job.get('id')} {state}: {why}")

    def __reduce__(self):
        # As ProblemError's: ``self.args`` holds the message, not the record __init__ takes.
        return (type(self), (self.job,), dict(self.__dict__))


def _rebuild(cls, args, kwargs):
    """An error made again by its constructor (the target of ``__reduce__``)."""
    return cls(*args, **kwargs)
