"""The studio's side of viser's WebSocket: every client message is judged before viser acts.

viser 1.1 trusts its clients: it applies any property a message names to the control
(its value, but also its range, options or label), casts the value with the control's
type (``float("abc")`` raises inside its event loop and logs a traceback), and a message
that does not decode (a lone surrogate in a file name is sent by the browser as bytes that
are not UTF-8) ends the sender's connection with a traceback. A string that cannot be
encoded (a lone surrogate) put into any GUI element stops the updates of every browser.
This module, applied to one server by :func:`gate` (and, once per process, by
:func:`install`), changes that:

- a control update goes through :meth:`studio.ui.checks.InputGuard.admit` first (value
  only, the control's own rule; a refusal is shown and the sender's widget set back);
- an upload is refused at its start when it announces more than :data:`MAX_UPLOAD_BYTES`
  or its parts exceed what it announced;
- a message that does not decode is dropped and reported (the connection stays);
- any other error of a message handler is reported in one log line, without a traceback;
- text that cannot be encoded, wherever it sits in the GUI's state, is escaped when
  viser encodes its messages (and logged), instead of ending every connection.

Only viser's own handler lists and, in viser's ``_infra`` module, its
``_message_consumer`` and its reference to ``msgspec`` are replaced.
"""

from __future__ import annotations

import inspect
import logging
import threading
import types
from collections.abc import Callable
from typing import Any

from studio.ui.checks import InputGuard, shown, value_text

log = logging.getLogger("studio.ui")

MAX_UPLOAD_BYTES = 1_000_000
"""Largest upload accepted [bytes] (a serve file's limit, :data:`studio.serve.params.MAX_SERVE_BYTES`)."""

_installed: list[bool] = []
_listeners: dict[int, Callable[[str], None]] = {}
"""Port of a studio's server -> its message line (undecodable messages are reported there)."""
_listeners_lock = threading.Lock()


def install() -> None:
    """Make viser drop (and report) a client message that does not decode instead of
    ending the connection with a traceback, and escape text that cannot be encoded in
    what it sends (idempotent, process-wide)."""
    if _installed:
        return
    from viser.infra import _infra

    async def _message_consumer(websocket: Any, handle_message: Callable[[Any], None], message_class: Any) -> None:
        while True:
            raw = await websocket.recv()  # a closed connection ends the loop as before
            try:
                if not isinstance(raw, bytes):
                    raise TypeError("a text frame (the studio reads binary messages only)")
                message = message_class.deserialize(raw)
            except Exception as err:  # noqa: BLE001 - any malformed message is dropped, the connection stays
                _undecodable(websocket, err)
                continue
            handle_message(message)

    _infra._message_consumer = _message_consumer
    msgpack = types.SimpleNamespace(
        **{**vars(_infra.msgspec.msgpack), "encode": _safe_encode(_infra.msgspec.msgpack.encode)}
    )
    _infra.msgspec = types.SimpleNamespace(**{**vars(_infra.msgspec), "msgpack": msgpack})  # type: ignore[assignment]  # viser's module only
    _installed.append(True)


def _undecodable(websocket: Any, err: Exception) -> None:
    kind = (
        "text that is not valid Unicode (such as a file name with a lone surrogate)"
        if isinstance(err, UnicodeError)
        else "a malformed message"
    )
    text = (
        f"**Refused:** a browser sent {kind}; the message was dropped ({type(err).__name__}: {shown(str(err))[:160]})."
    )
    log.warning("studio: %s", text)
    try:
        port = int(websocket.local_address[1])
    except Exception:  # noqa: BLE001 - no address: nobody to tell but the log
        return
    with _listeners_lock:
        report = _listeners.get(port)
    if report is not None:
        report(text)


def gate(server: Any, guard: InputGuard, report: Callable[[str], None]) -> None:
    """Put the studio's checks in front of ``server``'s message handlers (module doc);
    ``report`` shows a Markdown message in the studio."""
    from viser import _messages

    install()
    with _listeners_lock:
        _listeners[int(server.get_port())] = report
    gui = server.gui
    iface = gui._websock_interface
    handlers: dict[type, list[Callable[..., Any]]] = iface._incoming_handlers

    def resend(handle: Any) -> None:
        iface.queue_message(_messages.GuiUpdateMessage(handle._impl.uuid, {"value": handle.value}))

    guard.resend = resend

    def gui_update(original: Callable[..., Any]) -> Callable[..., Any]:
        async def handler(client_id: Any, message: Any) -> None:
            if guard.admit(client_id, message.uuid, message.updates):
                await original(client_id, message)

        return handler

    def upload_start(original: Callable[..., Any]) -> Callable[..., Any]:
        def handler(client_id: Any, message: Any) -> None:
            size, name = message.size_bytes, message.filename
            if not isinstance(size, int) or isinstance(size, bool) or not 0 <= size <= MAX_UPLOAD_BYTES:
                report(
                    f"**Upload refused:** `{value_text(name)}` announces {value_text(size)} bytes; at most {MAX_UPLOAD_BYTES} bytes are accepted."
                )
                return
            if not isinstance(name, str) or not isinstance(message.part_count, int) or message.part_count < 0:
                report("**Upload refused:** a malformed upload (file name or part count).")
                return
            original(client_id, message)

        return handler

    def upload_part(original: Callable[..., Any]) -> Callable[..., Any]:
        def handler(client_id: Any, message: Any) -> None:
            state = gui._current_file_upload_states.get(message.transfer_uuid)
            if state is not None:
                content = message.content
                sent = state["transferred_bytes"] + (len(content) if isinstance(content, (bytes, bytearray)) else 0)
                if (
                    not isinstance(content, (bytes, bytearray))
                    or sent > state["total_bytes"]
                    or not isinstance(message.part_index, int)
                ):
                    gui._current_file_upload_states.pop(message.transfer_uuid, None)
                    report(
                        f"**Upload refused:** `{value_text(state['filename'])}` sent more than the {state['total_bytes']} bytes it announced, or a malformed part."
                    )
                    return
            original(client_id, message)

        return handler

    special = {
        _messages.GuiUpdateMessage: gui_update,
        _messages.FileTransferStartUpload: upload_start,
        _messages.FileTransferPart: upload_part,
    }
    for message_cls, callbacks in handlers.items():
        for i, callback in enumerate(callbacks):
            if getattr(callback, "_studio_gated", False):
                continue
            inner = special[message_cls](callback) if message_cls in special else callback
            callbacks[i] = _quiet_errors(inner, message_cls.__name__, report)

    async def gate_connection(conn: Any) -> None:
        # each browser's own handlers (its ClientHandle's GUI and camera): errors logged in one line
        for message_cls, callbacks in conn._incoming_handlers.items():
            for i, callback in enumerate(callbacks):
                if not getattr(callback, "_studio_gated", False):
                    callbacks[i] = _quiet_errors(callback, message_cls.__name__, None)

    iface.on_client_connect(gate_connection)  # after viser's own: its handlers exist by then


def _quiet_errors(handler: Callable[..., Any], name: str, report: Callable[[str], None] | None) -> Callable[..., Any]:
    """``handler`` reporting its errors in one line (no traceback, the studio goes on);
    ``report``: also shown in the studio (None: the log only)."""

    def failed(err: Exception) -> None:
        text = (
            f"**Refused:** a browser's {name} could not be handled ({type(err).__name__}: {value_text(str(err), 160)})."
        )
        log.warning("studio: %s", text)
        if report is not None:
            report(text)

    if inspect.iscoroutinefunction(handler):

        async def wrapped_async(client_id: Any, message: Any) -> None:
            try:
                await handler(client_id, message)
            except Exception as err:  # noqa: BLE001 - a hostile message never logs a traceback
                failed(err)

        wrapped_async._studio_gated = True  # type: ignore[attr-defined]
        return wrapped_async

    def wrapped(client_id: Any, message: Any) -> None:
        try:
            handler(client_id, message)
        except Exception as err:  # noqa: BLE001 - a hostile message never logs a traceback
            failed(err)

    wrapped._studio_gated = True  # type: ignore[attr-defined]
    return wrapped


def _escaped(value: Any, depth: int = 0) -> Any:
    """A copy of a message payload (dicts, lists, tuples, strings) with lone surrogates
    escaped (:func:`~studio.ui.checks.shown`); other values as they are."""
    if isinstance(value, str):
        return shown(value)
    if depth > 64:
        return value
    if isinstance(value, dict):
        return {_escaped(k, depth + 1): _escaped(v, depth + 1) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_escaped(v, depth + 1) for v in value) if type(value) in (list, tuple) else value
    return value


def _safe_encode(encode: Callable[..., bytes]) -> Callable[..., bytes]:
    """viser's msgpack ``encode`` that escapes text which cannot be encoded (a lone
    surrogate anywhere in the GUI's state) instead of raising: one bad string would
    otherwise end every browser's connection, and every new one, until a restart."""

    def safe(obj: Any, *args: Any, **kwargs: Any) -> bytes:
        try:
            return encode(obj, *args, **kwargs)
        except UnicodeEncodeError:
            log.warning(
                "studio: a GUI message held text that is not valid Unicode: escaped before it reached the browsers"
            )
            return encode(_escaped(obj), *args, **kwargs)

    return safe
