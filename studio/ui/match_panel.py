"""The Match tab: serve a match from the library and record its points.

*Next serve* picks the robot's next serve by the paper's strategy
(:func:`studio.library.match.next_serve`), loads it and (with "play it") plays it; the
point buttons append to the library's match log (``matches.jsonl``), which keeps the
usage counters, and the Table I statistics below are refreshed.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from studio.errors import StudioError
from studio.ui.checks import Choice, Flag, Press, Text, choices
from studio.ui.host import StudioHost


class MatchPanel:
    """The Match tab's handles and actions.

    Args:
        host: the app (library folder).
        gui: the server's ``gui`` API; the handles go into its current container.
        show_entry: loads a library entry into the controls (and selects it in the list).
        play: starts the playback from its beginning (called when "play it" is ticked).
    """

    def __init__(
        self, host: StudioHost, gui: Any, *, show_entry: Callable[[Any], None], play: Callable[[], None]
    ) -> None:
        self.host = host
        self._show_entry = show_entry
        self._play = play
        self.current: str | None = None
        """Library id of the robot's current match serve (None before the first)."""
        gui.add_markdown(
            "Serve a match from the library: the next serve follows the paper's strategy (the least-used "
            "legal serve of another spin cluster than the previous one); record each point to the "
            "library's match log (`matches.jsonl`), which keeps the usage counters and the statistics."
        )
        self.match_next = gui.add_button("Next serve")
        self.match_play = gui.add_checkbox("play it", initial_value=True)
        self.match_opponent = gui.add_text("opponent", initial_value="")
        self.match_robot = gui.add_button_group("robot served", options=["won", "ace", "lost"])
        self.match_receive = gui.add_button_group("opponent served", options=["robot won", "robot lost"])
        self.match_md = gui.add_markdown("_no serve selected yet_")
        self.match_stats_md = gui.add_markdown("")
        guard = host.guard
        guard.add(self.match_next, Press("Next serve"))
        guard.add(self.match_play, Flag("play it"))
        guard.add(self.match_opponent, Text("opponent"))
        guard.add(self.match_robot, Choice("robot served", choices("won", "ace", "lost")))
        guard.add(self.match_receive, Choice("opponent served", choices("robot won", "robot lost")))
        guard.on_update(self.match_next, lambda _event: self.next_serve())
        guard.on_update(self.match_robot, lambda event: self.record_point("robot", event.target.value))
        guard.on_update(self.match_receive, lambda event: self.record_point("opponent", event.target.value))
        self.refresh_stats()

    def next_serve(self) -> None:
        """Select the robot's next serve (:func:`studio.library.match.next_serve`), load it and play it."""
        from studio.library.match import next_serve
        from studio.library.selection import serve_cluster, usage_count
        from studio.library.store import ServeLibrary

        try:
            entry = next_serve(
                ServeLibrary(self.host.library_dir), self.current
            )  # a pruned previous serve counts as none
        except StudioError as err:
            self.match_md.content = f"**No serve:** {err}"
            return
        previous = self.current
        self.current = entry.id
        self._show_entry(entry)
        self.match_md.content = (
            f"**Serve `{entry.data['name']}`** ({entry.id}): cluster {serve_cluster(entry)}, used {usage_count(entry)} times before"
            + (f"; previous `{previous}`" if previous else "")
            + ".  \nRecord the point when it is over."
        )
        if self.match_play.value:
            self._play()

    def record_point(self, server: str, outcome: str) -> None:
        """Record a point in the library's match log (:func:`studio.library.match.record_point`):
        ``server`` "robot" with outcome won/ace/lost of the current match serve, or
        "opponent" with robot won/robot lost."""
        from studio.library.match import record_point
        from studio.library.store import ServeLibrary

        outcomes = {"robot": ("won", "ace", "lost"), "opponent": ("robot won", "robot lost")}
        if outcome not in outcomes.get(server, ()):
            self.match_md.content = f"**Point not recorded:** {server!r} served: the outcome must be one of {', '.join(outcomes.get(server, ()))}, got {outcome!r}"
            return
        won = outcome in ("won", "ace", "robot won")
        try:
            points = record_point(
                ServeLibrary(self.host.library_dir), server=server, winner="robot" if won else "opponent",
                serve=self.current if server == "robot" else None, ace=outcome == "ace", opponent=self.match_opponent.value.strip(),
            )  # fmt: skip
        except StudioError as err:
            self.match_md.content = f"**Point not recorded:** {err}" + (
                " Press *Next serve* first." if server == "robot" and self.current is None else ""
            )
            return
        self.match_md.content = f"Point {len(points)} recorded: {server} served, {'robot' if won else 'opponent'} won{' (ace)' if outcome == 'ace' else ''}."
        self.refresh_stats()

    def refresh_stats(self) -> None:
        """Show the Table I statistics and the per-serve records of the library's match log."""
        from studio.library.match import MATCH_LOG, load_points, stats_report
        from studio.library.store import ServeLibrary

        lib = ServeLibrary(self.host.library_dir)
        try:
            self.match_stats_md.content = stats_report(lib.entries(), load_points(lib.folder / MATCH_LOG), compact=True)
        except StudioError as err:
            self.match_stats_md.content = f"**Match log unreadable:** {err}"
