"""The numbers at a glance: a floating panel over the 3D view.

:func:`serve_numbers` picks from an :class:`~studio.serve.evaluate.Evaluation` what a
coach reads first (verdict and first failing check, reward, ball speed and spin at the
net crossing and after the second bounce, net clearance, joint efforts);
:func:`overlay_markdown` lays them out, beside the pinned serve's ("A") when there is one.
Both are pure. :class:`OverlayPanel` is the floating viser panel holding that table, the
joint-effort verdict line, the camera presets, undo/redo and the A/B buttons; the app
wires the buttons.

Spin components are the velocity-aligned ones of :func:`studio.physics.ball.spin_components`
[rad/s]: topspin > 0, backspin < 0; sidespin > 0 turns counter-clockwise seen from above
(the ball curves to its left).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from studio.ui.camera import VIEW_NAMES

if TYPE_CHECKING:
    from studio.serve.efforts import EffortReport
    from studio.serve.evaluate import Evaluation

BADGES = {"legal": "LEGAL", "illegal": "ILLEGAL", "planner_failed": "NO PLAN", "collision": "COLLISION"}
"""Verdict words by evaluation status."""

UNDO, REDO = "Undo", "Redo"
"""The history buttons."""

PIN, RESTORE, CLEAR = "Pin as A", "Restore A", "Clear A"
"""The A/B buttons."""


@dataclass(frozen=True, slots=True)
class ServeNumbers:
    """What the overlay shows of one evaluated serve (None: not reached / not crossed)."""

    verdict: str
    """``LEGAL``, ``ILLEGAL``, ``NO PLAN`` or ``COLLISION``."""
    failing: str | None
    """The first failing check: its description and measured value (None when legal)."""
    reward: float
    """Reward F."""
    net_speed: float | None
    """Ball speed at the net crossing [m/s]."""
    net_topspin: float | None
    """Top (> 0) / back (< 0) spin at the net crossing [rad/s]."""
    net_sidespin: float | None
    """Sidespin at the net crossing [rad/s]."""
    bounce2_topspin: float | None
    """Top/back spin just after the second bounce [rad/s]."""
    bounce2_sidespin: float | None
    """Sidespin just after the second bounce [rad/s]."""
    clearance: float | None
    """Gap between the ball's bottom and the net top at the crossing [m]."""
    efforts: str | None
    """Joint efforts in short: ``within (a2 62 %)`` (the most used joint) or ``EXCEED gantry_x 131 %``."""


def _failing(ev: Evaluation) -> str | None:
    if ev.legal:
        return None
    failure = ev.legality.first_failure if ev.legality is not None else None
    if failure is not None:
        return f"{failure.label} ({failure.detail})" if failure.detail else failure.label
    return ev.reason or ev.failed_check


def _efforts_short(efforts: EffortReport | None) -> str | None:
    if efforts is None:
        return None
    if efforts.within:
        name, use = efforts.worst
        return f"within ({name} {100 * use:.0f} %)"
    over = ", ".join(f"{n} {100 * u:.0f} %" for n, u in zip(efforts.names, efforts.usage) if u > 1.0)
    return f"EXCEED {over}"


def serve_numbers(ev: Evaluation, efforts: EffortReport | None = None) -> ServeNumbers:
    """The overlay's numbers of ``ev`` (straight from ``ev.metrics``, unrounded)."""
    m = ev.metrics
    net = m.net if m is not None else None
    sb = m.second_bounce if m is not None else None
    return ServeNumbers(
        verdict=BADGES[ev.status],
        failing=_failing(ev),
        reward=float(ev.reward.total),
        net_speed=float(net["speed"]) if net else None,
        net_topspin=float(net["topspin"]) if net else None,
        net_sidespin=float(net["sidespin"]) if net else None,
        bounce2_topspin=float(sb["topspin"]) if sb else None,
        bounce2_sidespin=float(sb["sidespin"]) if sb else None,
        clearance=float(m.net_clearance) if m is not None and m.net_clearance is not None else None,
        efforts=_efforts_short(efforts),
    )


def topspin_text(value: float | None) -> str:
    """``topspin 118 rad/s`` / ``backspin 264 rad/s`` / ``-`` (None)."""
    if value is None:
        return "-"
    return f"{'topspin' if value >= 0 else 'backspin'} {abs(value):.0f} rad/s"


def sidespin_text(value: float | None) -> str:
    """``-76 rad/s`` (signed) / ``-``."""
    return "-" if value is None else f"{value:+.0f} rad/s"


def _rows(n: ServeNumbers) -> list[tuple[str, str]]:
    """(label, text) of each overlay row."""
    return [
        ("verdict", f"**{n.verdict}**"),
        ("first failing check", n.failing or "none"),
        ("reward F", f"{n.reward:+.3f}"),
        ("net: speed", "-" if n.net_speed is None else f"{n.net_speed:.2f} m/s"),
        ("net: top/back", topspin_text(n.net_topspin)),
        ("net: side", sidespin_text(n.net_sidespin)),
        ("2nd bounce: top/back", topspin_text(n.bounce2_topspin)),
        ("2nd bounce: side", sidespin_text(n.bounce2_sidespin)),
        ("net clearance", "-" if n.clearance is None else f"{100 * n.clearance:.1f} cm"),
        ("joint efforts", n.efforts or "-"),
    ]


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def overlay_markdown(now: ServeNumbers, pinned: ServeNumbers | None = None) -> str:
    """The overlay table: the current serve's numbers, and the pinned serve's beside them."""
    rows = _rows(now)
    if pinned is None:
        lines = ["| | now |", "|---|---|"]
        lines += [f"| {label} | {_cell(text)} |" for label, text in rows]
    else:
        lines = ["| | now | pinned A |", "|---|---|---|"]
        lines += [
            f"| {label} | {_cell(text)} | {_cell(other)} |" for (label, text), (_, other) in zip(rows, _rows(pinned))
        ]
    return "\n".join(lines)


class OverlayPanel:
    """The floating panel over the 3D view (top left).

    Args:
        gui: the server's ``gui`` API.
        width: panel width [CSS px].
    """

    def __init__(self, gui: Any, *, width: float = 430.0) -> None:
        self.panel = gui.add_panel()
        with self.panel.add_tab("At a glance"):
            self.status = gui.add_markdown("_evaluating..._")
            self.table = gui.add_markdown("")
            self.efforts = gui.add_markdown("")
            self.view = gui.add_button_group("View", options=list(VIEW_NAMES))
            self.history = gui.add_button_group("Edits", options=[UNDO, REDO])
            self.ab = gui.add_button_group("A/B", options=[PIN, RESTORE, CLEAR])
            self.note = gui.add_markdown("")
        self.panel.float(x=12, y=12, width=width)

    def show(self, now: ServeNumbers, pinned: ServeNumbers | None, *, status: str, efforts_line: str) -> None:
        """Show a new evaluation's numbers (and the pinned serve's)."""
        self.table.content = overlay_markdown(now, pinned)
        self.efforts.content = efforts_line
        self.status.content = status
