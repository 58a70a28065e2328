"""Server-side checks of every studio control: a browser widget's range is not a check.

Any WebSocket client of the studio's address (a browser tab, a script) can send any value
for any control: NaN, ``1e300``, text for a number, an option no dropdown lists, a serve
file ``../../secret``, 24 worker processes where the widget stops at 16. So every control
of the studio is registered with the app's :class:`InputGuard` together with a rule
(:class:`Number`, :class:`Choice`, :class:`Text`, :class:`Flag`, :class:`Press`,
:class:`Upload`) stating what it accepts, and

- :meth:`InputGuard.admit` judges each client message *before* viser applies it
  (:mod:`studio.ui.wire` puts it in front of viser's handler): a refused value never
  reaches the control; the sender's widget is set back and the studio's message line
  names the control, the value and what the control accepts;
- the change callback of every control re-checks its value first (values set by the
  studio itself, or by any path around the gate): a refused value is replaced by the last
  valid value of that control, with the same message, and the studio's own callbacks
  are not called. Exceptions of those callbacks end in the message line, never in a
  traceback.

Every refusal reads ``**Refused:** <control> = <value>: must be <what it accepts>; kept
<last valid value>.`` Text shown in the GUI goes through :func:`shown`: a lone surrogate
is not valid Unicode, cannot be encoded for the browsers, and would stop every client's
updates.
"""

from __future__ import annotations

import logging
import math
import numbers
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from studio.errors import InvalidInputError
from studio.storage.jsonfile import lone_surrogate

log = logging.getLogger("studio.ui")

MAX_TEXT = 200
"""Longest text accepted in a text field [characters] (the serve name's limit)."""


def shown(text: str) -> str:
    """``text`` as it can be shown in the GUI: lone surrogates (not valid Unicode, which
    no browser can be sent) written as their escapes (``\\ud800``)."""
    if lone_surrogate(text) is None:
        return text
    return text.encode("utf-8", "backslashreplace").decode("utf-8")


def value_text(value: Any, limit: int = 60) -> str:
    """A short, displayable rendering of a value a client sent."""
    if isinstance(value, bool):
        text = str(value).lower()
    elif isinstance(value, float):
        text = f"{value:g}"
    elif isinstance(value, int):
        digits = len(str(abs(value))) if abs(value) < 10**200 else 200
        text = str(value) if digits <= 20 else f"an integer of {digits} digits"
    else:
        text = repr(value)  # escapes lone surrogates and control characters
    text = shown(text)
    return text if len(text) <= limit else text[: limit - 3] + "..."


class Rule(Protocol):
    """What one control accepts."""

    @property
    def label(self) -> str:
        """The control's name, as the refusal message names it."""

    @property
    def client_settable(self) -> bool:
        """Whether a client may send this control a value at all."""

    def refusal(self, value: Any) -> str | None:
        """Why ``value`` is refused (``must be ...``), None when it is accepted."""


@dataclass(frozen=True)
class Number:
    """A finite number in ``[lo, hi]`` (``span`` gives a range that changes at run time),
    whole when ``integer``."""

    label: str
    lo: float = 0.0
    hi: float = 0.0
    unit: str = ""
    integer: bool = False
    span: Callable[[], tuple[float, float]] | None = None
    client_settable: bool = True

    def bounds(self) -> tuple[float, float]:
        """The accepted range now."""
        return self.span() if self.span is not None else (self.lo, self.hi)

    def allowed(self) -> str:
        lo, hi = self.bounds()
        unit = f" {self.unit}" if self.unit else ""
        if self.integer:
            return f"a whole number in [{int(lo)}, {int(hi)}]{unit}"
        return f"a number in [{lo:g}, {hi:g}]{unit}"

    def refusal(self, value: Any) -> str | None:
        why = f"must be {self.allowed()}"
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            return f"not a number; {why}"
        try:
            x = float(value)
        except (OverflowError, ValueError):
            return why
        if not math.isfinite(x):
            return why
        lo, hi = self.bounds()
        slack = (
            0.0 if self.integer else 1e-9 * max(1.0, abs(lo), abs(hi))
        )  # a slider step lands a rounding error off an end
        if not lo - slack <= x <= hi + slack:
            return why
        if self.integer and not x.is_integer():
            return why
        return None


@dataclass(frozen=True)
class Choice:
    """One of the listed options (``options`` is called at each check: lists that change
    at run time, such as the serve files, give their current entries)."""

    label: str
    options: Callable[[], Sequence[str]]
    client_settable: bool = True

    def allowed(self) -> str:
        opts = list(self.options())
        if len(opts) <= 8:
            return "one of " + ", ".join(f"'{shown(o)}'" for o in opts)
        return f"one of the {len(opts)} listed entries"

    def refusal(self, value: Any) -> str | None:
        if not isinstance(value, str) or value not in self.options():
            return f"must be {self.allowed()}"
        return None


def choices(*options: str) -> Callable[[], Sequence[str]]:
    """A fixed option list for :class:`Choice`."""
    fixed = tuple(options)
    return lambda: fixed


@dataclass(frozen=True)
class Text:
    """Text of valid Unicode, at most ``max_length`` characters, no control characters."""

    label: str
    max_length: int = MAX_TEXT
    client_settable: bool = True

    def refusal(self, value: Any) -> str | None:
        what = f"text of at most {self.max_length} characters"
        if not isinstance(value, str):
            return f"must be {what}"
        pos = lone_surrogate(value)
        if pos is not None:
            return f"not valid Unicode (a lone surrogate at position {pos}); must be {what}"
        if len(value) > self.max_length:
            return f"{len(value)} characters; must be {what}"
        if any(ord(ch) < 32 or ord(ch) == 127 for ch in value):
            return f"holds a control character; must be {what} without line breaks or control characters"
        return None


@dataclass(frozen=True)
class Flag:
    """A checkbox: true or false."""

    label: str
    client_settable: bool = True

    def refusal(self, value: Any) -> str | None:
        return None if isinstance(value, bool) else "must be true or false"


@dataclass(frozen=True)
class Press:
    """A button: a press sends ``true``."""

    label: str
    client_settable: bool = True

    def refusal(self, value: Any) -> str | None:
        return None if isinstance(value, bool) else "must be a button press (true)"


@dataclass(frozen=True)
class Upload:
    """An upload button: its value comes only from a file upload, never from a message."""

    label: str
    client_settable: bool = False

    def refusal(self, value: Any) -> str | None:
        ok = isinstance(getattr(value, "name", None), str) and isinstance(getattr(value, "content", None), bytes)
        return None if ok else "set only by uploading a file"


def refusal_message(label: str, value: Any, why: str, kept: Any = None, *, has_kept: bool = True) -> str:
    """``**Refused:** label = value: why; kept last.`` (displayable)."""
    text = f"**Refused:** {shown(label)} = `{value_text(value)}`: {why}"
    return text + (f"; kept `{value_text(kept)}`." if has_kept else ".")


def uuid_of(handle: Any) -> str:
    """viser's id of a GUI handle (the ``uuid`` of its messages)."""
    return str(handle._impl.uuid)


class InputGuard:
    """The rules of the studio's controls, their last valid values, and the studio's
    callbacks, called only with valid values (module doc).

    Args:
        report: shows a Markdown message (the studio's message line).
    """

    def __init__(self, report: Callable[[str], None]) -> None:
        self._report_to = report
        self._lock = threading.RLock()
        self._handles: dict[str, Any] = {}
        self._rules: dict[str, Rule] = {}
        self._last: dict[str, Any] = {}
        self._callbacks: dict[str, list[Callable[[Any], object]]] = {}
        self._local = threading.local()
        self.resend: Callable[[Any], None] | None = None
        """Sends a control's value to the browsers again (set by :func:`studio.ui.wire.gate`):
        the sender of a refused value sees the control's value again."""
        self.refusals: list[str] = []
        """The refusal messages, newest last (the latest 200)."""

    # -- registration ---------------------------------------------------------------

    def add(self, handle: Any, rule: Rule) -> Any:
        """Register ``handle`` with ``rule`` (its current value must pass); returns it."""
        why = rule.refusal(handle.value)
        if why is not None and not isinstance(rule, Upload):
            raise ValueError(f"control {rule.label!r}: initial value {handle.value!r} refused by its own rule: {why}")
        uuid = uuid_of(handle)
        with self._lock:
            self._handles[uuid] = handle
            self._rules[uuid] = rule
            self._last[uuid] = handle.value
            self._callbacks[uuid] = []
        register = (
            getattr(handle, "on_upload", None)
            or getattr(handle, "on_click", None)
            or getattr(handle, "on_update", None)
        )
        if register is not None:  # a progress bar has no callbacks (and takes no client values)
            register(lambda event, uuid=uuid: self._changed(uuid, event))
        return handle

    def on_update(self, handle: Any, callback: Callable[[Any], object]) -> None:
        """Call ``callback(event)`` after each accepted change (press, upload) of ``handle``."""
        with self._lock:
            self._callbacks[uuid_of(handle)].append(callback)

    def rule_of(self, handle: Any) -> Rule | None:
        """The rule ``handle`` was registered with (None: not registered)."""
        return self._rules.get(uuid_of(handle))

    def registered(self) -> set[str]:
        """The uuids of the registered controls."""
        return set(self._rules)

    # -- checks ---------------------------------------------------------------------

    def check(self, handle: Any) -> Any:
        """The value of ``handle`` if its rule accepts it; else :class:`InputRefused` with
        the refusal message (for code that reads a control before acting, as *Optimize*)."""
        uuid = uuid_of(handle)
        rule = self._rules[uuid]
        value = handle.value
        why = rule.refusal(value)
        if why is not None:
            raise InputRefused(refusal_message(rule.label, value, why, has_kept=False))
        return value

    def admit(self, client_id: Any, uuid: str, updates: Any) -> bool:
        """Whether a client's update of control ``uuid`` may be applied (module doc). A
        refused one is reported, and the sender's widget set back (:attr:`resend`)."""
        handle = self._handles.get(uuid)
        rule = self._rules.get(uuid)
        if handle is None or rule is None:
            self._report(
                f"**Refused:** a browser set a control the studio takes no input from (id `{value_text(uuid)}`)."
            )
            return False
        if not isinstance(updates, dict) or set(updates) != {"value"}:
            keys = sorted(shown(str(k)) for k in updates) if isinstance(updates, dict) else []
            self._report(
                f"**Refused:** a browser tried to change {', '.join(keys) or 'nothing'} of {shown(rule.label)}: only a control's value can be set."
            )
            return False
        value = updates["value"]
        if not rule.client_settable:
            fixed = (
                "set only by uploading a file"
                if isinstance(rule, Upload)
                else "shown by the studio, not set by a browser"
            )
            self._report(refusal_message(rule.label, value, fixed, has_kept=False))
            return False
        why = rule.refusal(value)
        current = handle.value
        if why is not None:
            self._report(
                refusal_message(rule.label, value, why, current, has_kept=not isinstance(rule, (Press, Upload)))
            )
            if self.resend is not None and not handle._impl.is_button:
                self.resend(handle)  # the sender's widget shows the kept value again
            return False
        with self._lock:
            if rule.refusal(current) is None:
                self._last[uuid] = current
        return True

    def _changed(self, uuid: str, event: Any) -> None:
        """viser's callback of every registered control: re-check, then the studio's callbacks."""
        if getattr(self._local, "restoring", False):
            return  # the value being put back
        handle, rule = self._handles[uuid], self._rules[uuid]
        value = handle.value
        why = rule.refusal(value)
        if why is not None:
            with self._lock:
                kept = self._last[uuid]
            self._restore(handle, kept)
            self._report(refusal_message(rule.label, value, why, kept, has_kept=not isinstance(rule, (Press, Upload))))
            return
        with self._lock:
            self._last[uuid] = value
            callbacks = list(self._callbacks[uuid])
        for callback in callbacks:
            try:
                callback(event)
            except Exception as err:  # noqa: BLE001 - shown in the studio; a callback never takes it down
                log.warning("studio: %s: %s: %s", rule.label, type(err).__name__, err)
                self._report(f"**{shown(rule.label)} failed:** {type(err).__name__}: {shown(str(err))}")

    def _restore(self, handle: Any, value: Any) -> None:
        """Put ``value`` back without running the callbacks (they saw no change)."""
        self._local.restoring = True
        try:
            handle.value = value
        except Exception as err:  # noqa: BLE001 - a value that cannot even be restored is reported
            log.warning("studio: cannot restore %s: %s", self._rules[uuid_of(handle)].label, err)
        finally:
            self._local.restoring = False

    def _report(self, text: str) -> None:
        text = shown(text)
        with self._lock:
            self.refusals.append(text)
            del self.refusals[:-200]
        log.info("studio: %s", text)
        self._report_to(text)


class InputRefused(InvalidInputError):
    """A control's value refused by its rule (the message is the refusal, Markdown)."""
