"""Serve files, the library and the dashboard's open requests, as the studio offers them.

:class:`FilesPanel` owns the "Serve file" picker (shipped examples and saved seeds) and
the "Files" folder of the Serve tab: save as seed, download/upload serve JSON, export the
evaluated serve to the library (refused beyond a joint's effort limit unless "Export
beyond effort limits" is ticked), load a library serve, and act on the dashboard's
"Open in studio" (``open-request.json`` in the library folder).

A file is only ever read from its folder: the "Serve file" choice must be one of the
listed files and must resolve inside its folder (:func:`load_serve_in`; a symlink out is
refused); a file whose name is not valid Unicode is not listed (it could not be shown).
An upload is read as a serve file is (:func:`read_upload`: at most
:data:`~studio.serve.params.MAX_SERVE_BYTES`, strict JSON through
:func:`studio.storage.jsonfile.parse_json`), and every refusal names the file and the
problem. The open-request watcher survives any request file.
"""

from __future__ import annotations

import json
import logging
import threading
from pathlib import Path
from typing import Any

from studio.errors import DataFileError, InvalidInputError, StudioError
from studio.optimize.workflow import export_evaluation
from studio.paths import example_serves_dir
from studio.serve.params import MAX_SERVE_BYTES, HandServe, load_serve, save_serve, serve_from_json
from studio.storage.jsonfile import lone_surrogate, parse_json
from studio.ui.checks import Choice, Flag, Press, Upload, shown
from studio.ui.host import StudioHost

log = logging.getLogger("studio.ui")

EXAMPLES_DIR = example_serves_dir()
"""The shipped example serves."""

CURRENT = "(current)"
"""The "Serve file" entry that leaves the controls alone."""

NO_LIBRARY_SERVE = "(none)"
"""The "Library serve" entry that loads nothing."""


def safe_name(name: str) -> str:
    """A file-name-safe version of a serve name (letters, digits, '-', '_')."""
    cleaned = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in name.strip())[:64].strip("_")
    if not cleaned:
        raise InvalidInputError("serve name must contain at least one letter or digit")
    return cleaned


def serve_files(folder: Path) -> tuple[dict[str, Path], list[str]]:
    """Serve JSON files in ``folder`` by file stem (sorted), and one line per file left
    out because its name is not valid Unicode (it could not be shown in a browser)."""
    try:
        if not folder.is_dir():
            return {}, []
        paths = sorted(folder.glob("*.json"))
    except OSError as err:
        return {}, [f"{shown(str(folder))}: cannot list: {err.strerror or err}"]
    listed: dict[str, Path] = {}
    problems: list[str] = []
    for path in paths:
        if lone_surrogate(path.name) is not None:
            problems.append(f"{shown(str(path))}: the file name is not valid Unicode (not listed; rename the file)")
        else:
            listed[path.stem] = path
    return listed, problems


def list_serves(folder: Path) -> dict[str, Path]:
    """Serve JSON files in ``folder`` by file stem (sorted; names that are not valid
    Unicode left out, :func:`serve_files`)."""
    return serve_files(folder)[0]


def inside(folder: Path, path: Path) -> bool:
    """Whether ``path`` resolves to a location inside ``folder``."""
    try:
        path.resolve().relative_to(folder.resolve())
        return True
    except (ValueError, OSError, RuntimeError):  # RuntimeError: a symlink loop
        return False


def load_serve_in(folder: Path, path: Path) -> HandServe:
    """:func:`~studio.serve.params.load_serve` of ``path``, refused (DataFileError) unless it
    resolves inside ``folder`` (``..`` or a symlink pointing out of it)."""
    if not inside(folder, path):
        raise DataFileError(
            shown(str(path)), f"resolves outside the folder {shown(str(folder))}; only files inside it are read"
        )
    return load_serve(path)


def read_upload(name: Any, content: Any) -> HandServe:
    """The serve of an uploaded file, or DataFileError naming the file and the problem:
    a name that is not valid Unicode, no bytes, more than
    :data:`~studio.serve.params.MAX_SERVE_BYTES`, not UTF-8, not strict JSON (NaN,
    infinity, huge numbers, nesting, lone surrogates), not a valid serve."""
    label = shown(name) if isinstance(name, str) else "upload"
    if not isinstance(name, str) or not name:
        raise DataFileError(label, "the upload has no file name")
    pos = lone_surrogate(name)
    if pos is not None:
        raise DataFileError(
            label,
            f"the file name is not valid Unicode (a lone surrogate at position {pos}); rename the file and upload it again",
        )
    if not isinstance(content, bytes):
        raise DataFileError(label, "the upload holds no file content")
    if not content:
        raise DataFileError(label, "the file is empty (0 bytes); a serve file is a JSON object")
    if len(content) > MAX_SERVE_BYTES:
        raise DataFileError(label, f"{len(content)} bytes, more than the {MAX_SERVE_BYTES} bytes a serve file may have")
    return serve_from_json(parse_json(content, label), source=label)


class FilesPanel:
    """The serve picker and the Files folder.

    :meth:`add_picker` and :meth:`add_folder` add the handles to the current GUI
    container (the picker at the top of the Serve tab, the folder at its end)."""

    def __init__(self, host: StudioHost) -> None:
        self.host = host
        self._quiet = False  # setting the dropdowns' options is not a user's choice
        self._library_ids: dict[str, str] = {}
        self._serve_choices: dict[str, tuple[Path, Path]] = {}
        """"Serve file" entry -> (its folder, its file)."""
        self._open_nonce: str | None = None
        self._open_problem: str | None = None
        self._open_lock = threading.Lock()
        self._watch_stop = threading.Event()

    # -- GUI ---------------------------------------------------------------------------

    def add_picker(self, gui: Any) -> None:
        """The "Serve file" dropdown (examples and saved seeds)."""
        self.serve_file = gui.add_dropdown("Serve file", options=[CURRENT], initial_value=CURRENT)
        guard = self.host.guard
        guard.add(self.serve_file, Choice("Serve file", lambda: [CURRENT, *self._serve_choices]))
        guard.on_update(self.serve_file, lambda _event: self._load_selected())

    def add_folder(self, gui: Any) -> None:
        """The "Files" folder: save, download, upload, export, library serve."""
        with gui.add_folder("Files"):
            self.save_button = gui.add_button("Save as seed")
            self.download_button = gui.add_button("Download JSON")
            self.upload_button = gui.add_upload_button("Upload JSON", mime_type="application/json")
            self.export_button = gui.add_button("Export to library")
            self.export_beyond = gui.add_checkbox(
                "Export beyond effort limits", initial_value=False,
                hint="Raise each exceeded joint's effort limit to the plan's peak for this export (recorded in the entry)",
            )  # fmt: skip
            self.library_pick = gui.add_dropdown(
                "Library serve", options=[NO_LIBRARY_SERVE], initial_value=NO_LIBRARY_SERVE
            )
        guard = self.host.guard
        guard.add(self.save_button, Press("Save as seed"))
        guard.add(self.download_button, Press("Download JSON"))
        guard.add(self.upload_button, Upload("Upload JSON"))
        guard.add(self.export_button, Press("Export to library"))
        guard.add(self.export_beyond, Flag("Export beyond effort limits"))
        guard.add(self.library_pick, Choice("Library serve", lambda: [NO_LIBRARY_SERVE, *self._library_ids]))
        guard.on_update(self.save_button, lambda _event: self.save_seed())
        guard.on_update(self.download_button, lambda event: self.download(event.client))
        guard.on_update(self.upload_button, lambda _event: self.upload(self.upload_button.value))
        guard.on_update(self.export_button, lambda _event: self.export())
        guard.on_update(self.library_pick, lambda _event: self.load_library_serve())
        self.refresh_serve_files()
        self.refresh_library()

    # -- serve files -------------------------------------------------------------------

    def refresh_serve_files(self) -> None:
        """List the saved seeds and the examples in the "Serve file" dropdown."""
        serves_dir = self.host.serves_dir
        choices = {stem: (serves_dir, path) for stem, path in list_serves(serves_dir).items()}
        if serves_dir.resolve() != EXAMPLES_DIR.resolve():
            choices.update(
                {f"example/{stem}": (EXAMPLES_DIR, path) for stem, path in list_serves(EXAMPLES_DIR).items()}
            )
        self._quiet = True
        try:
            self._serve_choices = {**self._serve_choices, **choices}  # old and new entries valid while the list changes
            self.serve_file.options = [CURRENT, *choices]
            self.serve_file.value = CURRENT
            self._serve_choices = choices
        finally:
            self._quiet = False

    def _load_selected(self) -> None:
        if self._quiet or self.serve_file.value == CURRENT:
            return
        key = self.serve_file.value
        choice = self._serve_choices.get(key)
        if choice is None:  # the guard lets only listed entries through
            self.host.message(f"**Cannot load** `{shown(key)}`: not a listed serve file")
            return
        folder, path = choice
        try:
            self.host.load(load_serve_in(folder, path))
            self.host.message(f"Loaded `{shown(key)}`.")
        except (StudioError, OSError) as err:
            self.host.message(f"**Cannot load {shown(key)}:** {err}")

    def save_seed(self) -> None:
        """Save the controls' serve as ``<serves_dir>/<name>.json``."""
        serves_dir = self.host.serves_dir
        try:
            serve = self.host.controls().serve
            serves_dir.mkdir(parents=True, exist_ok=True)
            path = serves_dir / f"{safe_name(serve.name)}.json"
            if not inside(serves_dir, path):
                raise InvalidInputError(f"serve name {serve.name!r} leaves the serves folder")
            save_serve(path, serve)
            self.refresh_serve_files()
            self.host.message(f"Saved seed `{path.name}` in `{serves_dir}`.")
        except (StudioError, OSError) as err:
            self.host.message(f"**Save failed:** {err}")

    def download(self, client: Any) -> None:
        """Send the controls' serve as a JSON file to ``client``'s browser (None: nobody)."""
        try:
            serve = self.host.controls().serve
            data = (json.dumps(serve.to_json(), indent=2) + "\n").encode()
            if client is not None:
                client.send_file_download(f"{safe_name(serve.name)}.json", data)
        except StudioError as err:
            self.host.message(f"**Download failed:** {err}")

    def upload(self, file: Any) -> bool:
        """Load an uploaded serve JSON (``file.name``, ``file.content`` bytes) read by
        :func:`read_upload`; a bad file is refused with a message naming it and the
        problem. True if loaded."""
        try:
            serve = read_upload(getattr(file, "name", None), getattr(file, "content", None))
        except StudioError as err:
            self.host.message(f"**Upload rejected:** {err}")
            return False
        self.host.load(serve)
        self.host.message(f"Loaded upload `{shown(file.name)}`.")
        return True

    # -- library -----------------------------------------------------------------------

    def refresh_library(self) -> None:
        """List the library's serves in the "Library serve" dropdown (errors go to the message)."""
        from studio.library.store import ServeLibrary

        try:
            entries = ServeLibrary(self.host.library_dir).entries()
        except StudioError as err:
            entries = []
            self.host.message(f"**Library unreadable:** {err}")
        ids = {shown(f"{e.data['name']} [{e.id}]"): e.id for e in entries}
        self._quiet = True
        try:
            self._library_ids = {**self._library_ids, **ids}  # old and new entries valid while the list changes
            self.library_pick.options = [NO_LIBRARY_SERVE, *ids]
            self._library_ids = ids
            self.library_pick.value = NO_LIBRARY_SERVE
        finally:
            self._quiet = False

    def load_library_serve(self) -> None:
        """Load the serve chosen in the "Library serve" dropdown."""
        from studio.library.store import ServeLibrary

        if self._quiet or self.library_pick.value == NO_LIBRARY_SERVE:
            return
        try:
            entry = ServeLibrary(self.host.library_dir).get(self._library_ids[self.library_pick.value])
            self.host.load(entry.serve)
            self.host.message(f"Loaded library serve `{entry.id}`.")
        except (StudioError, KeyError, OSError) as err:
            self.host.message(f"**Cannot load library serve:** {err}")

    def show_library_entry(self, entry: Any) -> None:
        """Load a library entry into the controls and select it in the "Library serve" list."""
        self.refresh_library()
        label = next((k for k, v in self._library_ids.items() if v == entry.id), None)
        self._quiet = True
        try:
            if label is not None:
                self.library_pick.value = label
        finally:
            self._quiet = False
        self.host.load(entry.serve)

    def export(self) -> None:
        """Add the newest evaluation to the library (refused beyond an effort limit unless
        "Export beyond effort limits" is ticked: then the raised limits are recorded)."""
        evaluation, efforts = self.host.latest()
        if evaluation is None:
            self.host.message("**Export failed:** nothing evaluated yet")
            return
        limits = efforts.peak_limits() if efforts is not None and self.export_beyond.value else {}
        library_dir = self.host.library_dir
        try:
            entry = export_evaluation(
                library_dir,
                evaluation,
                context=self.host.context,
                task=self.host.controls().task,
                provenance={"kind": "hand-designed", "tool": "studio"},
                effort_limits=limits,
            )
            verdict = "legal" if evaluation.legal else f"NOT legal ({evaluation.reason})"
            beyond = (
                f" Effort limits raised on purpose: {', '.join(f'{n} {v:g}' for n, v in limits.items())}."
                if limits
                else ""
            )
            self.host.message(
                f"Exported `{evaluation.serve.name}` ({verdict}) to `{library_dir}` as `{entry.id}`.{beyond}"
            )
            self.refresh_library()
        except (StudioError, OSError) as err:
            self.host.message(f"**Export failed:** {err}")

    # -- the dashboard's "Open in studio" ---------------------------------------------

    def poll_open_request(self, *, act: bool = True) -> bool:
        """Load the serve a dashboard asked for (``open-request.json`` in the library
        folder, :func:`studio.library.store.request_open`), once per request. True if loaded."""
        with self._open_lock:
            return self._poll_open_request(act)

    def _poll_open_request(self, act: bool) -> bool:
        from studio.library.store import ServeLibrary, read_open_request

        library_dir = self.host.library_dir
        try:
            req = read_open_request(library_dir)
        except (StudioError, OSError) as err:
            problem = f"**Open request ignored:** {err}"
            if act and problem != self._open_problem:  # once per problem, not twice a second
                self.host.message(problem)
            self._open_problem = problem
            return False
        self._open_problem = None
        if req is None or req.nonce == self._open_nonce:
            return False
        self._open_nonce = req.nonce
        if not act:
            return False
        try:
            entry = ServeLibrary(library_dir).get(req.id)
        except StudioError as err:
            self.host.message(f"**Cannot open library serve** `{req.id}`: {err}")
            return False
        self.show_library_entry(entry)
        self.host.message(f"Opened library serve `{entry.id}` ({entry.data['name']}) from the dashboard.")
        return True

    def poll_safely(self) -> bool:
        """:meth:`poll_open_request` that never raises: anything a request file (or the
        library it names) can do wrong ends in the message line. True if loaded."""
        try:
            return self.poll_open_request()
        except Exception as err:  # noqa: BLE001 - the watcher outlives any bad file
            problem = f"**Open request ignored:** {type(err).__name__}: {err}"
            log.warning("studio: %s", problem)
            if problem != self._open_problem:
                self.host.message(problem)
            self._open_problem = problem
            return False

    def watch_open_requests(self, period: float = 0.5) -> threading.Thread:
        """Poll for open requests every ``period`` [s] in a daemon thread (until
        :meth:`stop_watching`)."""
        self._watch_stop.clear()

        def loop() -> None:
            while not self._watch_stop.wait(period):
                self.poll_safely()

        thread = threading.Thread(target=loop, name="studio-open-requests", daemon=True)
        thread.start()
        return thread

    def stop_watching(self) -> None:
        """End the open-request watcher."""
        self._watch_stop.set()
