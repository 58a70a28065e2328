"""Refuse WebSocket connections from foreign web pages (cross-site WebSocket hijacking).

A browser lets any page open ``ws://127.0.0.1:8080``: binding the studio to localhost does
not stop a site the user visits from driving its sliders, saving seeds or exporting to the
library. Browsers always send the page's ``Origin`` with a WebSocket handshake, so the
studio accepts a handshake only when

- its ``Origin`` names the same host and port as the request's ``Host`` (the studio's own
  page), and
- for a studio bound to a loopback address, that host is a loopback name (``localhost``,
  ``127.0.0.1``, ``[::1]``): a DNS-rebinding page has its own host name there.

Clients that send no ``Origin`` (scripts, not browsers) are accepted. viser 1.1 has no
origin option, so :func:`install` wraps the ``process_request`` hook its server hands to
``websockets`` (the only module it patches is viser's own server module, and only once).
"""

from __future__ import annotations

import http
import types
from collections.abc import Callable
from typing import Any
from urllib.parse import urlsplit

LOOPBACK_HOSTS = frozenset({"localhost", "127.0.0.1", "::1"})
"""Host names of the local machine's loopback interface."""

_installed: list[bool] = []


def origin_allowed(origin: str | None, host_header: str | None, *, bound_host: str) -> bool:
    """True when a WebSocket handshake with these headers may connect (module doc)."""
    if origin is None:
        return True
    if not host_header:
        return False
    page = urlsplit(origin)
    if page.scheme not in ("http", "https") or not page.netloc:
        return False
    served = urlsplit(f"//{host_header}")
    if (page.hostname, page.port) != (served.hostname, served.port):
        return False
    if bound_host in LOOPBACK_HOSTS or bound_host == "":
        return (page.hostname or "") in LOOPBACK_HOSTS
    return True


def guarded_process_request(inner: Callable[..., Any] | None, *, bound_host: str) -> Callable[..., Any]:
    """A websockets ``process_request`` that answers 403 to a foreign-origin handshake and
    hands every other request to ``inner``."""

    def process_request(connection: Any, request: Any) -> Any:
        headers = request.headers
        if headers.get("Upgrade", "").lower() == "websocket" and not origin_allowed(
            headers.get("Origin"), headers.get("Host"), bound_host=bound_host
        ):
            return connection.respond(
                http.HTTPStatus.FORBIDDEN, "foreign origin refused: open the studio from its own address\n"
            )
        return inner(connection, request) if inner is not None else None

    return process_request


def install() -> None:
    """Make every viser server started from now on refuse foreign origins (idempotent)."""
    if _installed:
        return
    import websockets
    from viser.infra import _infra

    real_serve = websockets.asyncio.server.serve

    def serve(handler: Any, host: Any = None, port: Any = None, **kwargs: Any) -> Any:
        kwargs["process_request"] = guarded_process_request(kwargs.get("process_request"), bound_host=str(host or ""))
        return real_serve(handler, host, port, **kwargs)

    server_ns = types.SimpleNamespace(**{**vars(websockets.asyncio.server), "serve": serve})
    asyncio_ns = types.SimpleNamespace(**{**vars(websockets.asyncio), "server": server_ns})
    # viser's module only; setattr because a namespace stands in for the websockets module.
    setattr(_infra, "websockets", types.SimpleNamespace(**{**vars(websockets), "asyncio": asyncio_ns}))  # noqa: B010
    _installed.append(True)
