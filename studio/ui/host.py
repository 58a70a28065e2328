"""What the studio's panels may ask of the app (:class:`studio.ui.app.StudioApp`).

The panels (files, optimization jobs, match, overlay) get the app as a
:class:`StudioHost` and use nothing else of it, so each panel can be read, and tested,
on its own.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    from studio.serve.efforts import EffortReport
    from studio.serve.evaluate import Evaluation, EvaluationContext
    from studio.serve.params import HandServe
    from studio.ui.checks import InputGuard
    from studio.ui.controls import Controls


class StudioHost(Protocol):
    """The app as the panels see it."""

    context: EvaluationContext
    """Robot, tosses, planner and models of the live evaluation (the worker's thread)."""
    serves_dir: Path
    """Folder of hand-designed serves (seeds)."""
    library_dir: Path
    """Serve library folder."""
    guard: InputGuard
    """The checks of every control (each panel registers its controls' rules there)."""

    def load(self, serve: HandServe) -> None:
        """Put ``serve`` into the controls and evaluate it (one undo step)."""

    def controls(self) -> Controls:
        """The controls as a validated snapshot (InvalidInputError names a bad control)."""

    def side_and_task(self) -> tuple[str, str]:
        """The toss side and reward task chosen in the controls."""

    def message(self, text: str) -> None:
        """Show a Markdown message under the tabs."""

    def latest(self) -> tuple[Evaluation | None, EffortReport | None]:
        """The newest published evaluation and its joint-effort report."""
