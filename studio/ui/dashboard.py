"""Panel dashboard over a serve library folder (``studio/library/store.py``).

What it shows:

- the library table (``pn.widgets.Tabulator``) with filters on toss side, task, legality
  and spin cluster;
- the ball state at the net crossing as a scatter (the paper's Fig. 3b): horizontal speed
  vs total spin, or topspin vs sidespin, points coloured by :func:`spin_cluster`; and the
  spin direction as a polar plot (:func:`spin_polar`: the spin axis as the receiver sees
  it, topspin to the right, sidespin up, radius its size);
- with a reference match file (``reference``, the Ace public format): real players' and
  the Ace robot's serves beside the library's in both plots, marked apart
  (:mod:`studio.ui.reference`: each serve flown from its measured state after the racket
  to the net with the project's flight model);
- the selected serve: joint commands ``u(t)`` of the 8 joints and the predicted ball path
  seen from above (x-y) and from the side (x-z), with the table and the net drawn;
- "Open in studio": asks a studio running on the same library folder to load the serve
  into its controls (:func:`studio.library.store.request_open`) and brings up the studio's
  browser tab (if its URL is known); a download of the serve JSON that the studio (and
  ``serve-studio evaluate``) load;
- a reload button that re-reads the library folder.

Match statistics (the paper's Table I and a per-serve table) come from the library's
``matches.jsonl``. Optimization convergence: for the serves whose provenance names a HEBO
run folder (``serve-studio optimize|train``), the best reward so far against evaluations,
one line per run, the selected serve's run highlighted with its per-evaluation rewards;
run folders are only read inside ``runs_dir`` (default ``./runs``, where the CLI writes
them). A corrupt library or run log (``DataFileError``) is shown as a message naming the
file and the field; nothing raises out of a callback.

World frame (``DESIGN.md``): origin at the centre of the playing surface, +X towards the
receiver, +Z up, SI units. Spin components are the paper's velocity-aligned ones
(:func:`studio.physics.ball.spin_components`): topspin > 0, backspin < 0, sidespin > 0 curving
the ball to its left.
"""

from __future__ import annotations

import io
import json
import math
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
import pandas as pd
import panel as pn
from bokeh.models import ColumnDataSource, Range1d
from bokeh.models.widgets.tables import NumberFormatter
from bokeh.plotting import figure

from studio.errors import StudioError
from studio.library.selection import entry_cluster, net_state, spin_cluster  # noqa: F401 - re-exported
from studio.library.store import INDEX_NAME, LibraryEntry, ServeLibrary
from studio.optimize.workflow import provenance_run
from studio.physics.court import DEFAULT_COURT
from studio.serve.params import LimitScale
from studio.ui.reference import HUMAN, ROBOT, ReferenceServes, cached_reference_serves

CLUSTERS = ("topspin", "backspin", "sidespin", "mixed", "no spin", "no net crossing")
"""Spin cluster labels, in legend order."""
CLUSTER_COLORS = {
    "topspin": "#d62728",
    "backspin": "#1f77b4",
    "sidespin": "#2ca02c",
    "mixed": "#9467bd",
    "no spin": "#7f7f7f",
    "no net crossing": "#bcbd22",
}
"""Colour of each cluster in the scatter and the table."""
ALL = "all"
"""Filter value that keeps every row."""
AlertType = Literal["primary", "secondary", "success", "danger", "warning", "info", "light", "dark"]
"""A panel ``Alert``'s ``alert_type`` (the status line's kind)."""
SCATTER_AXES = ("horizontal speed vs total spin", "topspin vs sidespin")
"""The two scatter views."""
COLUMNS = (
    "name",
    "side",
    "task",
    "legal",
    "reward",
    "cluster",
    "speed_h",
    "spin",
    "topspin",
    "sidespin",
    "cork",
    "clearance",
    "limits",
    "provenance",
    "created",
    "id",
)
"""Table columns (``speed_h`` [m/s] and spins [rad/s] at the net crossing, ``clearance`` [m],
``limits``: the dynamic limit expansion the serve needs, :func:`limits_text`)."""
TITLES = {
    "speed_h": "net v_h [m/s]",
    "spin": "net |ω| [rad/s]",
    "topspin": "net top [rad/s]",
    "sidespin": "net side [rad/s]",
    "cork": "net cork [rad/s]",
    "clearance": "net clearance [m]",
    "limits": "limits [x robot's]",
}
"""Table column titles with units."""


def limits_text(scale: LimitScale) -> str:
    """``"1"`` for the robot's own limits, else the factors, e.g. ``"v 1.1, a 1.5, j 1.5"``."""
    if scale.is_identity:
        return "1"
    return f"v {scale.velocity:g}, a {scale.acceleration:g}, j {scale.jerk:g}"


def library_table(entries: list[LibraryEntry]) -> pd.DataFrame:
    """One row per serve with the columns of ``COLUMNS`` (NaN where the net state is absent)."""
    rows = []
    for e in entries:
        d = e.data
        net = net_state(d)
        prov = d.get("provenance")
        prov_text = ", ".join(f"{k}={v}" for k, v in prov.items()) if isinstance(prov, dict) else str(prov or "")
        rows.append(
            {
                "name": str(d["name"]),
                "side": str(d["side"]),
                "task": str(d.get("task") or ""),
                "legal": bool(d["legal"]),
                "reward": float(d["reward"]),
                "cluster": entry_cluster(d),
                "speed_h": net.speed_h if net else math.nan,
                "spin": net.spin if net else math.nan,
                "topspin": net.topspin if net else math.nan,
                "sidespin": net.sidespin if net else math.nan,
                "cork": net.cork if net else math.nan,
                "clearance": net.clearance if net else math.nan,
                "limits": limits_text(e.limit_scale),
                "provenance": prov_text,
                "created": str(d["created"]),
                "id": e.id,
            }
        )
    return pd.DataFrame(rows, columns=list(COLUMNS))


def filter_table(
    df: pd.DataFrame, *, side: str = ALL, task: str = ALL, legal: str = ALL, cluster: str = ALL
) -> pd.DataFrame:
    """Rows matching the filters (``ALL`` keeps everything; ``legal`` is ``"legal"``/``"illegal"``)."""
    mask = np.ones(len(df), dtype=bool)
    if side != ALL:
        mask &= (df["side"] == side).to_numpy()
    if task != ALL:
        mask &= (df["task"] == task).to_numpy()
    if legal != ALL:
        mask &= (df["legal"] == (legal == "legal")).to_numpy()
    if cluster != ALL:
        mask &= (df["cluster"] == cluster).to_numpy()
    return df[mask].reset_index(drop=True)


def _table_outline(view: str) -> list[tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], str]]:
    """Table top, net and floor as line segments for the ball path views (``"top"``/``"side"``)."""
    c = DEFAULT_COURT
    hx, hy = c.length / 2, c.width / 2
    if view == "top":
        return [
            (np.array([-hx, hx, hx, -hx, -hx]), np.array([-hy, -hy, hy, hy, -hy]), "#2b6cb0"),
            (np.array([-hx, hx]), np.array([0.0, 0.0]), "#a0aec0"),
            (np.array([0.0, 0.0]), np.array([-hy - c.net_post_offset, hy + c.net_post_offset]), "#000000"),
        ]
    return [
        (np.array([-hx, hx]), np.array([0.0, 0.0]), "#2b6cb0"),
        (np.array([0.0, 0.0]), np.array([0.0, c.net_height]), "#000000"),
    ]


def joint_plot(arrays: dict[str, Any], *, title: str = "joint commands u(t)") -> Any:
    """Bokeh figure of the 8 joint commands ``u`` (M, 8) against ``t`` (M,) [s]."""
    from bokeh.palettes import Category10

    t = np.asarray(arrays["t"], dtype=float)
    u = np.asarray(arrays["u"], dtype=float)
    names = [str(n) for n in np.asarray(arrays.get("joint_names", []))] or [f"joint {i}" for i in range(u.shape[1])]
    t_toss = float(np.asarray(arrays.get("t_toss", 0.0)))
    clock = "from the preparation's start; the toss starts at the dashed line" if t_toss > 0 else "toss clock"
    fig = figure(
        title=title,
        height=320,
        sizing_mode="stretch_width",
        x_axis_label=f"t [s] ({clock})",
        y_axis_label="u [m or rad]",
    )
    for i in range(u.shape[1]):
        fig.line(
            t,
            u[:, i],
            color=Category10[10][i % 10],
            line_width=2,
            legend_label=names[i] if i < len(names) else f"joint {i}",
        )
    if t_toss > 0:
        from bokeh.models.annotations.geometry import Span

        fig.add_layout(
            Span(location=t_toss, dimension="height", line_dash="dashed", line_color="#4a5568", line_width=1)
        )
    fig.legend.click_policy = "hide"
    fig.legend.label_text_font_size = "8pt"
    fig.add_layout(fig.legend[0], "right")
    return fig


def ball_path_plot(arrays: dict[str, Any], *, view: str) -> Any:
    """Bokeh figure of the predicted ball path ``ball_p`` (K, 3) from above or from the side.

    Args:
        arrays: the serve's arrays (``entry.arrays()``).
        view: ``"top"`` (x-y plane) or ``"side"`` (x-z plane).
    """
    p = np.asarray(arrays["ball_p"], dtype=float)
    j = 1 if view == "top" else 2
    label = "y [m]" if view == "top" else "z [m]"
    title = "ball path, top view" if view == "top" else "ball path, side view"
    fig = figure(
        title=title,
        height=300,
        sizing_mode="stretch_width",
        x_axis_label="x [m] (towards receiver)",
        y_axis_label=label,
        match_aspect=True,
    )
    for x, y, color in _table_outline(view):
        fig.line(x, y, color=color, line_width=3)
    if len(p):
        fig.line(p[:, 0], p[:, j], color="#e53e3e", line_width=2, legend_label="ball")
        fig.scatter(p[[0, -1], 0], p[[0, -1], j], size=7, color=["#38a169", "#000000"])
    hx = DEFAULT_COURT.length / 2
    fig.x_range = Range1d(start=-hx - 0.6, end=hx + 0.3)
    return fig


REFERENCE_STYLE = {
    ROBOT: {"marker": "triangle", "color": "#4a5568", "label": "Ace robot serves (reference)"},
    HUMAN: {"marker": "square", "color": "#dd6b20", "label": "human serves (reference)"},
}
"""How the reference serves are drawn: grey triangles (robot), orange squares (human)."""


def _reference_layer(fig: Any, reference: ReferenceServes | None, xy: Any) -> None:
    """Draw the reference serves (under the library's points) with ``xy(rows) -> (x, y)``."""
    if reference is None:
        return
    for who, style in REFERENCE_STYLE.items():
        rows = reference.of(who)
        if not len(rows):
            continue
        x, y = xy(rows)
        src = ColumnDataSource({"x": x, "y": y, "name": [f"{who}: {p} {r}" for p, r in zip(rows["player"], rows["rally"])], "cluster": [f"reference ({who})"] * len(rows),
                                **{c: rows[c].to_numpy(float) for c in ("speed_h", "spin", "topspin", "sidespin")}})  # fmt: skip
        fig.scatter(
            "x",
            "y",
            source=src,
            marker=style["marker"],
            size=7,
            color=style["color"],
            alpha=0.45,
            legend_label=f"{style['label']}: {len(rows)}",
        )


def spin_scatter(
    df: pd.DataFrame,
    *,
    axes: str = SCATTER_AXES[0],
    selected_id: str | None = None,
    reference: ReferenceServes | None = None,
) -> Any:
    """Bokeh scatter of the net-crossing state of the rows of ``df``, coloured by cluster,
    over the ``reference`` serves (if any)."""
    if axes == SCATTER_AXES[0]:
        xcol, ycol, xl, yl = "speed_h", "spin", "horizontal speed at the net [m/s]", "total spin at the net [rad/s]"
    else:
        xcol, ycol, xl, yl = (
            "topspin",
            "sidespin",
            "topspin at the net [rad/s] (< 0: backspin)",
            "sidespin at the net [rad/s]",
        )
    fig = figure(
        title=f"ball at the net crossing: {axes}",
        height=360,
        sizing_mode="stretch_width",
        x_axis_label=xl,
        y_axis_label=yl,
        tools="pan,wheel_zoom,box_zoom,reset,hover",
    )
    fig.hover.tooltips = [
        ("serve", "@name"),
        ("cluster", "@cluster"),
        (xcol, f"@{xcol}{{0.00}}"),
        (ycol, f"@{ycol}{{0.0}}"),
    ]
    _reference_layer(fig, reference, lambda rows: (rows[xcol].to_numpy(float), rows[ycol].to_numpy(float)))
    ok = df[np.isfinite(df[xcol].to_numpy(dtype=float)) & np.isfinite(df[ycol].to_numpy(dtype=float))]
    for cluster in CLUSTERS:
        sub = ok[ok["cluster"] == cluster]
        if len(sub):
            src = ColumnDataSource(
                {
                    "x": sub[xcol].to_numpy(float),
                    "y": sub[ycol].to_numpy(float),
                    "name": sub["name"].tolist(),
                    "cluster": sub["cluster"].tolist(),
                    xcol: sub[xcol].to_numpy(float),
                    ycol: sub[ycol].to_numpy(float),
                }
            )
            fig.scatter("x", "y", source=src, size=11, color=CLUSTER_COLORS[cluster], legend_label=cluster, alpha=0.85)
    if selected_id is not None:
        sel = ok[ok["id"] == selected_id]
        if len(sel):
            fig.scatter(
                sel[xcol].to_numpy(float),
                sel[ycol].to_numpy(float),
                size=20,
                fill_alpha=0.0,
                line_color="black",
                line_width=2,
            )
    _legend_outside(fig)
    return fig


POLAR_SPOKES = ((0.0, "topspin"), (90.0, "sidespin +"), (180.0, "backspin"), (270.0, "sidespin -"))
"""Labelled directions of the polar plot [deg from +topspin, counter-clockwise]."""


def _polar_grid(fig: Any, r_max: float) -> None:
    """Rings every 100 rad/s up to ``r_max`` and the labelled spokes."""
    from bokeh.models.annotations.labels import Label

    theta = np.linspace(0.0, 2.0 * np.pi, 181)
    for r in np.arange(100.0, r_max + 1e-9, 100.0):
        fig.line(r * np.cos(theta), r * np.sin(theta), color="#cbd5e0", line_width=1)
        fig.add_layout(
            Label(
                x=r * np.cos(np.radians(60)),
                y=r * np.sin(np.radians(60)),
                text=f"{r:.0f}",
                text_font_size="7pt",
                text_color="#718096",
            )
        )
    for deg in np.arange(0.0, 360.0, 45.0):
        a = np.radians(deg)
        fig.line([0.0, r_max * np.cos(a)], [0.0, r_max * np.sin(a)], color="#e2e8f0", line_width=1)
    for deg, text in POLAR_SPOKES:
        a = np.radians(deg)
        fig.add_layout(
            Label(
                x=1.04 * r_max * np.cos(a),
                y=1.04 * r_max * np.sin(a),
                text=text,
                text_font_size="8pt",
                text_align="center",
                text_baseline="middle",
            )
        )


def spin_polar(df: pd.DataFrame, *, selected_id: str | None = None, reference: ReferenceServes | None = None) -> Any:
    """Polar plot of the spin direction at the net crossing: each serve at angle
    ``atan2(sidespin, topspin)`` (0 = pure topspin, 90 deg = sidespin > 0, 180 deg =
    backspin) and radius ``hypot(topspin, sidespin)`` [rad/s] (the spin the receiver sees,
    without the cork part about the flight direction); the library's serves by cluster
    colour, the ``reference`` serves marked apart."""
    fig = figure(title="spin direction at the net: angle atan2(side, top), radius |(top, side)| [rad/s]", height=380, sizing_mode="stretch_width", match_aspect=True,
                 tools="pan,wheel_zoom,reset,hover", x_axis_label="topspin [rad/s] (< 0: backspin)", y_axis_label="sidespin [rad/s]")  # fmt: skip
    fig.hover.tooltips = [
        ("serve", "@name"),
        ("cluster", "@cluster"),
        ("topspin", "@topspin{0}"),
        ("sidespin", "@sidespin{0}"),
    ]
    ok = df[np.isfinite(df["topspin"].to_numpy(dtype=float)) & np.isfinite(df["sidespin"].to_numpy(dtype=float))]
    radii = [np.hypot(ok["topspin"].to_numpy(float), ok["sidespin"].to_numpy(float))]
    if reference is not None and len(reference.table):
        radii.append(np.hypot(reference.table["topspin"].to_numpy(float), reference.table["sidespin"].to_numpy(float)))
    r_max = max(100.0, 100.0 * np.ceil(max((float(r.max()) for r in radii if len(r)), default=100.0) / 100.0))
    _polar_grid(fig, r_max)
    _reference_layer(fig, reference, lambda rows: (rows["topspin"].to_numpy(float), rows["sidespin"].to_numpy(float)))
    for cluster in CLUSTERS:
        sub = ok[ok["cluster"] == cluster]
        if len(sub):
            src = ColumnDataSource({"x": sub["topspin"].to_numpy(float), "y": sub["sidespin"].to_numpy(float), "name": sub["name"].tolist(), "cluster": sub["cluster"].tolist(),
                                    "topspin": sub["topspin"].to_numpy(float), "sidespin": sub["sidespin"].to_numpy(float)})  # fmt: skip
            fig.scatter("x", "y", source=src, size=11, color=CLUSTER_COLORS[cluster], legend_label=cluster, alpha=0.85)
    if selected_id is not None:
        sel = ok[ok["id"] == selected_id]
        if len(sel):
            fig.scatter(
                sel["topspin"].to_numpy(float),
                sel["sidespin"].to_numpy(float),
                size=20,
                fill_alpha=0.0,
                line_color="black",
                line_width=2,
            )
    fig.scatter(
        [-1.15 * r_max, 1.15 * r_max], [-1.15 * r_max, 1.15 * r_max], alpha=0.0
    )  # room for the spoke labels (match_aspect keeps the rings round)
    _legend_outside(fig)
    return fig


def _legend_outside(fig: Any) -> None:
    """Move the legend to the right of the plot (it hid points in the corner)."""
    if fig.legend:
        fig.legend.label_text_font_size = "8pt"
        fig.legend.click_policy = "hide"
        fig.add_layout(fig.legend[0], "right")


def load_reference(path: str | Path | None) -> tuple[ReferenceServes | None, str]:
    """The reference serves of a match file and a Markdown line about them (or the error)."""
    if path is None:
        return None, ""
    try:
        ref = cached_reference_serves(path)
    except (StudioError, OSError) as err:
        return None, f"**Cannot read the reference serves:** {_text(str(err))}"
    return ref, _text(ref.summary()).replace("\\_", "_")


def run_folder(entry: LibraryEntry, runs_dir: Path) -> Path | None:
    """The HEBO run folder named by ``entry``'s provenance, if it lies inside ``runs_dir``.

    Relative run paths are taken from the current folder (as the CLI wrote them). A path
    outside ``runs_dir`` is not followed (the index is user data)."""
    run = provenance_run(entry.data)
    if run is None:
        return None
    path = Path(run).resolve()
    root = runs_dir.resolve()
    return path if path.is_relative_to(root) and path.is_dir() else None


def run_histories(entries: list[LibraryEntry], runs_dir: Path) -> tuple[dict[str, Any], list[str]]:
    """Convergence histories of the entries' runs: ({entry id: RunHistory}, error messages)."""
    from studio.optimize.optimizer import load_run_history

    out: dict[str, Any] = {}
    errors: list[str] = []
    cache: dict[Path, Any] = {}
    for e in entries:
        folder = run_folder(e, runs_dir)
        if folder is None:
            continue
        if folder not in cache:
            try:
                cache[folder] = load_run_history(folder)
            except StudioError as err:
                cache[folder] = None
                errors.append(str(err))
        if cache[folder] is not None:
            out[e.id] = cache[folder]
    return out, errors


def convergence_plot(
    histories: dict[str, Any], *, names: dict[str, str] | None = None, selected_id: str | None = None
) -> Any:
    """Bokeh figure: best reward so far vs evaluations, one grey line per run; the
    selected serve's run in colour with each evaluation's reward (legal: green, not: red)."""
    fig = figure(
        height=320,
        sizing_mode="stretch_width",
        title="HEBO convergence: best reward so far",
        x_axis_label="evaluations",
        y_axis_label="reward F",
    )
    names = names or {}
    for sid, h in histories.items():
        if sid == selected_id or not len(h.reward):
            continue
        fig.line(np.arange(1, len(h.reward) + 1, dtype=float), h.best_so_far, color="#a0aec0", line_width=1, alpha=0.8)
    h = histories.get(selected_id) if selected_id is not None else None
    if h is not None and selected_id is not None and len(h.reward):
        n = np.arange(1, len(h.reward) + 1, dtype=float)
        fig.scatter(n[h.legal], h.reward[h.legal], size=3, color="#2ca02c", alpha=0.5, legend_label="legal evaluation")
        fig.scatter(
            n[~h.legal], h.reward[~h.legal], size=3, color="#d62728", alpha=0.3, legend_label="illegal / failed"
        )
        fig.line(
            n,
            h.best_so_far,
            color="#1f2937",
            line_width=2.5,
            legend_label=f"best so far: {names.get(selected_id, selected_id)}",
        )
        fig.legend.location = "bottom_right"
    return fig


def convergence_text(histories: dict[str, Any], errors: list[str], *, selected_id: str | None, runs_dir: Path) -> str:
    """Markdown summary under the convergence plot."""
    lines = []
    if not histories:
        lines.append(
            f"No HEBO run logs for these serves under `{runs_dir}` (serves from `serve-studio optimize` or `train` link their run folder)."
        )
    else:
        runs = {id(h): h for h in histories.values()}
        best = [float(h.best_so_far[-1]) for h in runs.values() if len(h.reward)]
        lines.append(
            f"{len(runs)} runs; final best training reward median {np.median(best):+.3f} (min {min(best):+.3f}, max {max(best):+.3f})."
        )
        h = histories.get(selected_id) if selected_id is not None else None
        if h is not None and len(h.reward):
            k = int(np.argmax(h.reward))
            lines.append(
                f"Selected serve's run `{h.run_dir.name}` ({h.task}, {h.side} toss): {len(h.reward)} evaluations, "
                f"{int(h.legal.sum())} legal, best {h.reward[k]:+.3f} at evaluation {k + 1}, {h.seconds.sum():.0f} s of evaluation."
            )
    lines.extend(f"**Cannot read a run log:** {_text(e)}" for e in errors)
    return "\n\n".join(lines)


def _text(message: str) -> str:
    """Escape a message for Markdown text outside code spans (file paths hold underscores)."""
    return message.replace("\\", "\\\\").replace("_", "\\_").replace("*", "\\*")


class LibraryDashboard:
    """The dashboard state and its Panel layout (``self.layout``).

    Args:
        library_dir: the serve library folder (may be missing or empty: a message says so).
        studio_url: URL of a running studio (``serve-studio app``), linked from the serve view.
        runs_dir: folder holding HEBO run folders (convergence plots); runs named by the
            library outside it are not read.
        reference: a match file in the Ace public format whose serves are drawn beside
            the library's (:mod:`studio.ui.reference`); None: none.
    """

    def __init__(
        self,
        library_dir: str | Path,
        *,
        studio_url: str | None = None,
        runs_dir: str | Path = "runs",
        reference: str | Path | None = None,
    ) -> None:
        self.library = ServeLibrary(library_dir)
        self.reference, reference_text = load_reference(reference)
        self.studio_url = studio_url
        self.runs_dir = Path(runs_dir)
        self.histories: dict[str, Any] = {}
        self.run_errors: list[str] = []
        self.entries: list[LibraryEntry] = []
        self.table = library_table([])
        self.error: str | None = None
        """Message of the last library or serve error (None when all is well)."""

        self._build_filters()
        self._build_table()
        self._build_views(reference_text)
        self._build_serve_actions(studio_url)
        self.selected_id: str | None = None
        self._wire()
        self.layout = self._build_layout()
        self.reload()

    # -- layout ------------------------------------------------------------------------

    def _build_filters(self) -> None:
        """The status line, the reload button, the table filters and the scatter's axes."""
        self.status = pn.pane.Alert("", alert_type="info", visible=False, sizing_mode="stretch_width")
        self.reload_button = pn.widgets.Button(label="Reload library", color="primary", width=160)
        self.side = pn.widgets.Select(label="Toss side", options=[ALL], value=ALL, width=130)
        self.task = pn.widgets.Select(label="Task", options=[ALL], value=ALL, width=170)
        self.legal = pn.widgets.Select(label="Legality", options=[ALL, "legal", "illegal"], value=ALL, width=130)
        self.cluster = pn.widgets.Select(label="Spin cluster", options=[ALL, *CLUSTERS], value=ALL, width=160)
        self.axes = pn.widgets.RadioButtonGroup(label="Scatter", options=list(SCATTER_AXES), value=SCATTER_AXES[0])

    def _build_table(self) -> None:
        """The library table (one row selectable)."""
        self.tabulator = pn.widgets.Tabulator(
            self.table,
            show_index=False,
            selectable=1,
            disabled=True,
            pagination="local",
            page_size=15,
            sizing_mode="stretch_width",
            titles=TITLES,
            formatters={
                "legal": {"type": "tickCross"},
                "reward": NumberFormatter(format="0.000"),
                "clearance": NumberFormatter(format="0.000"),
                **{
                    k: NumberFormatter(format="0.00" if k == "speed_h" else "0")
                    for k in ("speed_h", "spin", "topspin", "sidespin", "cork")
                },
            },
        )

    def _build_views(self, reference_text: str) -> None:
        """The spin plots, the selected serve's panes, convergence and match statistics."""
        self.scatter = pn.pane.Bokeh(spin_scatter(self.table, reference=self.reference), sizing_mode="stretch_width")
        self.polar = pn.pane.Bokeh(spin_polar(self.table, reference=self.reference), sizing_mode="stretch_width")
        self.reference_info = pn.pane.Markdown(
            reference_text, sizing_mode="stretch_width", visible=bool(reference_text)
        )
        self.detail_title = pn.pane.Markdown("", sizing_mode="stretch_width")
        self.detail_error = pn.pane.Alert("", alert_type="danger", visible=False, sizing_mode="stretch_width")
        self.joints = pn.pane.Bokeh(None, sizing_mode="stretch_width")
        self.match = pn.pane.Markdown("", sizing_mode="stretch_width")
        self.convergence = pn.pane.Bokeh(None, sizing_mode="stretch_width")
        self.convergence_info = pn.pane.Markdown("", sizing_mode="stretch_width")
        self.top_view = pn.pane.Bokeh(None, sizing_mode="stretch_width")
        self.side_view = pn.pane.Bokeh(None, sizing_mode="stretch_width")
        self.studio_link = pn.pane.Markdown("", sizing_mode="stretch_width")

    def _build_serve_actions(self, studio_url: str | None) -> None:
        """The selected serve's "Download serve JSON" and "Open in studio" buttons."""
        self.download = pn.widgets.FileDownload(
            callback=self._serve_json,
            filename="serve.json",
            label="Download serve JSON",
            color="success",
            width=220,
            disabled=True,
        )
        self.open_button = pn.widgets.Button(label="Open in studio", color="primary", width=160, disabled=True)
        self.open_button.on_click(self._on_open_click)
        if studio_url:  # the browser side: bring up the studio tab (named, so it is reused)
            self.open_button.js_on_click(args={"url": studio_url}, code="window.open(url, 'serve-studio')")

    def _wire(self) -> None:
        """The widgets' callbacks: reload, filters, scatter axes, table selection."""
        self.reload_button.on_click(lambda _event: self.reload())
        for w in (self.side, self.task, self.legal, self.cluster):
            w.param.watch(lambda _event: self._refresh(), "value")
        self.axes.param.watch(lambda _event: self._redraw_scatter(), "value")
        self.tabulator.param.watch(lambda _event: self._on_selection(), "selection")

    def _build_layout(self) -> pn.Column:
        """The page: header, filters, table, plots beside the selected serve, convergence, matches."""
        header = pn.pane.Markdown(f"## Serve library\n`{self.library.folder}`", sizing_mode="stretch_width")
        return pn.Column(
            pn.Row(header, self.reload_button, sizing_mode="stretch_width"),
            self.status,
            pn.Row(self.side, self.task, self.legal, self.cluster),
            self.tabulator,
            pn.Row(
                pn.Column(self.axes, self.scatter, self.polar, self.reference_info, sizing_mode="stretch_width"),
                pn.Column(
                    self.detail_title,
                    self.detail_error,
                    pn.Row(self.open_button, self.download, self.studio_link, sizing_mode="stretch_width"),
                    self.top_view,
                    self.side_view,
                    sizing_mode="stretch_width",
                ),
                sizing_mode="stretch_width",
            ),
            self.joints,
            pn.pane.Markdown("### Optimization convergence"),
            self.convergence,
            self.convergence_info,
            pn.pane.Markdown("### Match statistics"),
            self.match,
            sizing_mode="stretch_width",
        )

    # -- data --------------------------------------------------------------------------

    def _match_text(self) -> str:
        """Table I-like statistics from the library's match log (``matches.jsonl``), as Markdown."""
        from studio.library.match import MATCH_LOG, load_points, stats_report

        path = self.library.folder / MATCH_LOG
        if not path.exists():
            return f"No match log yet (`{MATCH_LOG}`): record points with `serve-studio library record {self.library.folder} ...`."
        try:
            return stats_report(self.entries, load_points(path))
        except StudioError as err:
            return f"**Cannot read the match log:** {_text(str(err))}"

    def reload(self) -> None:
        """Re-read the library folder; a corrupt library leaves an error message, no exception."""
        self.error = None
        try:
            self.entries = self.library.entries()
        except StudioError as err:
            self.entries = []
            self.error = str(err)
        self.table = library_table(self.entries)
        for widget, column in ((self.side, "side"), (self.task, "task")):
            options = [ALL, *sorted(set(self.table[column]))]
            if widget.value not in options:
                widget.value = ALL
            widget.options = options
        if self.error is not None:
            self._show_status(f"**Cannot read the library:** {_text(self.error)}", "danger")
        elif not self.entries:
            what = "no index.json" if not self.library.index_path.exists() else "it holds no serves"
            self._show_status(
                f"The library `{self.library.folder}` is empty ({what}). Export serves with `serve-studio evaluate --export` or from the studio.",
                "warning",
            )
        else:
            n_legal = int(self.table["legal"].sum())
            self._show_status(f"{len(self.entries)} serves ({n_legal} legal) in `{self.library.index_path}`.", "info")
        self.match.object = self._match_text()
        self.histories, self.run_errors = run_histories(self.entries, self.runs_dir)
        self._refresh()

    def filtered(self) -> pd.DataFrame:
        """The table rows that pass the current filters."""
        return filter_table(
            self.table, side=self.side.value, task=self.task.value, legal=self.legal.value, cluster=self.cluster.value
        )

    def entry(self, serve_id: str) -> LibraryEntry | None:
        """The loaded entry with ``serve_id``."""
        return next((e for e in self.entries if e.id == serve_id), None)

    # -- view updates ------------------------------------------------------------------

    def _on_open_click(self, _event: Any) -> None:
        """The "Open in studio" button (its outcome is shown in the status line)."""
        self.open_in_studio()

    def _show_status(self, message: str, kind: AlertType) -> None:
        self.status.object = message
        self.status.alert_type = kind
        self.status.visible = True

    def _refresh(self) -> None:
        df = self.filtered()
        self.tabulator.value = df
        ids = df["id"].tolist()
        target = self.selected_id if self.selected_id in ids else (ids[0] if ids else None)
        self._show_serve(target)  # before the selection, so that its watcher finds nothing new
        self.tabulator.selection = [ids.index(target)] if target is not None else []
        self._redraw_scatter()

    def _redraw_scatter(self) -> None:
        df = self.filtered()
        self.scatter.object = spin_scatter(
            df, axes=self.axes.value, selected_id=self.selected_id, reference=self.reference
        )
        self.polar.object = spin_polar(df, selected_id=self.selected_id, reference=self.reference)
        shown = {sid: self.histories[sid] for sid in df["id"] if sid in self.histories}
        self.convergence.object = convergence_plot(
            shown, names=dict(zip(df["id"], df["name"])), selected_id=self.selected_id
        )
        self.convergence_info.object = convergence_text(
            shown, self.run_errors, selected_id=self.selected_id, runs_dir=self.runs_dir
        )

    def _on_selection(self) -> None:
        df = self.tabulator.value
        sel = [i for i in self.tabulator.selection if 0 <= i < len(df)]
        if sel:
            serve_id = str(df.iloc[sel[0]]["id"])
            if serve_id != self.selected_id:
                self._show_serve(serve_id)
                self._redraw_scatter()

    def _show_serve(self, serve_id: str | None) -> None:
        """Show the serve ``serve_id`` (None: nothing selected); array errors become a message."""
        self.selected_id = serve_id
        entry = self.entry(serve_id) if serve_id is not None else None
        self.detail_error.visible = False
        if entry is None:
            self.detail_title.object = "### Serve\nNo serve selected." if self.entries else ""
            for pane in (self.joints, self.top_view, self.side_view):
                pane.object = None
            self.download.disabled = True
            self.open_button.disabled = True
            self.studio_link.object = ""
            return
        d = entry.data
        net = net_state(d)
        net_text = (
            f"net crossing: {net.speed_h:.2f} m/s horizontal, spin {net.spin:.0f} rad/s (top {net.topspin:+.0f}, side {net.sidespin:+.0f}), clearance {net.clearance * 100:.1f} cm"
            if net
            else "no net crossing"
        )
        verdict = "legal" if d["legal"] else "ILLEGAL"
        self.detail_title.object = f"### {_text(str(d['name']))}\n`{entry.id}` · {d['side']} toss · task {_text(str(d.get('task')))} · {verdict} · reward {float(d['reward']):.3f} · {entry_cluster(d)} · {net_text}"
        self.download.filename = f"{entry.id}.json"
        self.download.disabled = False
        self.open_button.disabled = False
        where = f"the studio at [{self.studio_url}]({self.studio_url})" if self.studio_url else "the studio"
        self.studio_link.object = (
            f"*Open in studio* loads this serve into the controls of {where} when it runs on this library "
            f"(`serve-studio app --library {self.library.folder}`); otherwise upload the downloaded JSON there."
        )
        try:
            arrays = entry.arrays()
        except StudioError as err:
            self.error = str(err)
            self.detail_error.object = f"**Cannot read the serve's arrays:** {_text(str(err))}"
            self.detail_error.visible = True
            for pane in (self.joints, self.top_view, self.side_view):
                pane.object = None
            return
        self.joints.object = joint_plot(arrays)
        self.top_view.object = ball_path_plot(arrays, view="top")
        self.side_view.object = ball_path_plot(arrays, view="side")

    def open_in_studio(self) -> bool:
        """Ask a studio running on this library to load the selected serve
        (:func:`studio.library.store.request_open`); the outcome goes to the status line."""
        from studio.library.store import request_open

        if self.selected_id is None:
            return False
        try:
            request_open(self.library.folder, self.selected_id)
        except StudioError as err:
            self._show_status(f"**Cannot ask the studio to open the serve:** {_text(str(err))}", "danger")
            return False
        self._show_status(
            f"Asked the studio to open `{self.selected_id}` (a studio running on `{self.library.folder}` loads it within a second).",
            "success",
        )
        return True

    def _serve_json(self) -> io.StringIO:
        """The selected serve as a serve JSON file (``serve-studio/serve@1``)."""
        entry = self.entry(self.selected_id) if self.selected_id is not None else None
        if entry is None:
            return io.StringIO("")
        return io.StringIO(json.dumps(entry.serve.to_json(), indent=2) + "\n")


def build_dashboard(
    library_dir: str | Path,
    *,
    studio_url: str | None = None,
    runs_dir: str | Path = "runs",
    reference: str | Path | None = None,
) -> pn.viewable.Viewable:
    """The dashboard layout over ``library_dir`` (for notebooks: display it or ``.servable()``)."""
    pn.extension("tabulator")
    return LibraryDashboard(library_dir, studio_url=studio_url, runs_dir=runs_dir, reference=reference).layout


def run_dashboard(
    *,
    library_dir: str | Path,
    host: str = "127.0.0.1",
    port: int = 5006,
    studio_url: str | None = None,
    runs_dir: str | Path = "runs",
    reference: str | Path | None = None,
) -> None:
    """Serve the dashboard on http://host:port (blocking; localhost only by default).

    Each browser session gets its own dashboard reading ``library_dir`` (the reference
    serves of ``reference`` are computed once and shared). Pass ``host="0.0.0.0"`` to
    expose it on purpose (then any origin may connect).
    """
    pn.extension("tabulator")
    if reference is not None:
        print(
            f"serve-studio dashboard: {load_reference(reference)[1]}", flush=True
        )  # computed once, before the first session
    origins = ["*"] if host in ("0.0.0.0", "::") else [f"{host}:{port}", f"localhost:{port}", f"127.0.0.1:{port}"]
    print(
        f"serve-studio dashboard: http://{'127.0.0.1' if host in ('0.0.0.0', '::') else host}:{port} (library {Path(library_dir)}/{INDEX_NAME})"
    )
    pn.serve(
        {
            "/": lambda: (
                LibraryDashboard(library_dir, studio_url=studio_url, runs_dir=runs_dir, reference=reference).layout
            )
        },
        address=host,
        port=port,
        show=False,
        websocket_origin=origins,
        title="Serve library",
    )
