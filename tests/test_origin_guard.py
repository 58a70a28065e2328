"""The studio's WebSocket accepts its own page and scripts, and refuses foreign pages."""

from __future__ import annotations

import socket

import pytest
import viser
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from studio.ui.origin_guard import install, origin_allowed


@pytest.mark.parametrize(
    ("origin", "host", "bound", "ok"),
    [
        (None, "127.0.0.1:8080", "127.0.0.1", True),  # a script, not a browser
        ("http://127.0.0.1:8080", "127.0.0.1:8080", "127.0.0.1", True),
        ("http://localhost:8080", "localhost:8080", "127.0.0.1", True),
        ("http://evil.example", "127.0.0.1:8080", "127.0.0.1", False),
        ("http://127.0.0.1:9999", "127.0.0.1:8080", "127.0.0.1", False),  # another local app
        ("http://evil.example:8080", "evil.example:8080", "127.0.0.1", False),  # DNS rebinding
        ("http://192.168.1.5:8080", "192.168.1.5:8080", "0.0.0.0", True),  # served on the LAN on purpose
        ("null", "127.0.0.1:8080", "127.0.0.1", False),  # sandboxed frame / file:// page
    ],
)
def test_origin_rule(origin: str | None, host: str, bound: str, ok: bool) -> None:
    assert origin_allowed(origin, host, bound_host=bound) is ok


def test_a_live_server_refuses_a_foreign_origin() -> None:
    install()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    try:
        url = f"ws://127.0.0.1:{server.get_port()}"
        with pytest.raises(InvalidStatus) as refused:
            connect(url, origin="http://evil.example", open_timeout=10).close()  # type: ignore[arg-type]
        assert refused.value.response.status_code == 403
        connect(url, origin=f"http://127.0.0.1:{server.get_port()}", open_timeout=10).close()  # type: ignore[arg-type]
        connect(url, open_timeout=10).close()
    finally:
        server.stop()
