"""Serve files, the library and the dashboard's open requests, as the studio offers them.

:class:`FilesPanel` owns the "Serve file" picker (shipped examples and saved seeds) and
the "Files" folder of the Serve tab: save as seed, download/upload serve JSON, export the
evaluated serve to the library (refused beyond a joint's effort limit unless "Export
beyond effort limits" is ticked), load a library serve, and act on the dashboard's
"Open in studio" (``open-request.json`` in the library folder).
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import Any

from studio.errors import InvalidInputError, StudioError
from studio.paths import example_serves_dir
from studio.serve.params import load_serve, save_serve, serve_from_json
from studio.ui.host import StudioHost

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


def list_serves(folder: Path) -> dict[str, Path]:
    """Serve JSON files in ``folder`` by file stem (sorted)."""
    if not folder.is_dir():
        return {}
    return {p.stem: p for p in sorted(folder.glob("*.json"))}


def inside(folder: Path, path: Path) -> bool:
    """Whether ``path`` resolves to a location inside ``folder``."""
    try:
        path.resolve().relative_to(folder.resolve())
        return True
    except ValueError:
        return False


class FilesPanel:
    """The serve picker and the Files folder.

    :meth:`add_picker` and :meth:`add_folder` add the handles to the current GUI
    container (the picker at the top of the Serve tab, the folder at its end)."""

    def __init__(self, host: StudioHost) -> None:
        self.host = host
        self._quiet = False  # setting the dropdowns' options is not a user's choice
        self._library_ids: dict[str, str] = {}
        self._open_nonce: str | None = None
        self._open_lock = threading.Lock()

    # -- GUI ---------------------------------------------------------------------------

    def add_picker(self, gui: Any) -> None:
        """The "Serve file" dropdown (examples and saved seeds)."""
        self.serve_file = gui.add_dropdown("Serve file", options=[CURRENT], initial_value=CURRENT)
        self.serve_file.on_update(lambda _event: self._load_selected())

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
            self.library_pick = gui.add_dropdown("Library serve", options=[NO_LIBRARY_SERVE], initial_value=NO_LIBRARY_SERVE)
        self.save_button.on_click(lambda _event: self.save_seed())
        self.download_button.on_click(lambda event: self.download(event.client))
        self.upload_button.on_upload(lambda _event: self.upload(self.upload_button.value))
        self.export_button.on_click(lambda _event: self.export())
        self.library_pick.on_update(lambda _event: self.load_library_serve())
        self.refresh_serve_files()
        self.refresh_library()

    # -- serve files -------------------------------------------------------------------

    def refresh_serve_files(self) -> None:
        """List the saved seeds and the examples in the "Serve file" dropdown."""
        serves_dir = self.host.serves_dir
        examples = [f"example/{k}" for k in list_serves(EXAMPLES_DIR) if serves_dir.resolve() != EXAMPLES_DIR.resolve()]
        self._quiet = True
        try:
            self.serve_file.options = [CURRENT, *list_serves(serves_dir), *examples]
            self.serve_file.value = CURRENT
        finally:
            self._quiet = False

    def _load_selected(self) -> None:
        if self._quiet or self.serve_file.value == CURRENT:
            return
        key = self.serve_file.value
        folder, stem = (EXAMPLES_DIR, key.split("/", 1)[1]) if key.startswith("example/") else (self.host.serves_dir, key)
        try:
            self.host.load(load_serve(folder / f"{stem}.json"))
            self.host.message(f"Loaded `{stem}`.")
        except StudioError as err:
            self.host.message(f"**Cannot load {stem}:** {err}")

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

    def upload(self, file: Any) -> None:
        """Load an uploaded serve JSON (``file.name``, ``file.content`` bytes); bad files are reported."""
        try:
            data = json.loads(file.content.decode("utf-8"))
            self.host.load(serve_from_json(data, source=file.name))
            self.host.message(f"Loaded upload `{file.name}`.")
        except (UnicodeDecodeError, json.JSONDecodeError) as err:
            self.host.message(f"**Upload rejected:** {file.name}: not valid JSON ({err})")
        except StudioError as err:
            self.host.message(f"**Upload rejected:** {err}")

    # -- library -----------------------------------------------------------------------

    def refresh_library(self) -> None:
        """List the library's serves in the "Library serve" dropdown (errors go to the message)."""
        from studio.library.store import ServeLibrary

        try:
            entries = ServeLibrary(self.host.library_dir).entries()
        except StudioError as err:
            entries = []
            self.host.message(f"**Library unreadable:** {err}")
        self._library_ids = {f"{e.data['name']} [{e.id}]": e.id for e in entries}
        self._quiet = True
        try:
            self.library_pick.options = [NO_LIBRARY_SERVE, *self._library_ids]
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
        except (StudioError, KeyError) as err:
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
        from studio.library.store import ServeLibrary

        evaluation, efforts = self.host.latest()
        if evaluation is None:
            self.host.message("**Export failed:** nothing evaluated yet")
            return
        raised = efforts.raised_to_peaks() if efforts is not None and self.export_beyond.value else None
        limits = {n: float(lim) for n, lim in zip(raised.names, raised.limit) if n in raised.raised} if raised is not None else {}
        library_dir = self.host.library_dir
        try:
            entry = ServeLibrary(library_dir).add(
                evaluation, provenance={"kind": "hand-designed", "tool": "studio"}, task=self.host.controls().task,
                preparation=self.host.context.preparation(evaluation.serve.side), effort_limits=limits,
            )  # fmt: skip
            verdict = "legal" if evaluation.legal else f"NOT legal ({evaluation.reason})"
            beyond = f" Effort limits raised on purpose: {', '.join(f'{n} {v:g}' for n, v in limits.items())}." if limits else ""
            self.host.message(f"Exported `{evaluation.serve.name}` ({verdict}) to `{library_dir}` as `{entry.id}`.{beyond}")
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
        except StudioError as err:
            if act:
                self.host.message(f"**Open request ignored:** {err}")
            return False
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

    def watch_open_requests(self, period: float = 0.5) -> None:
        """Poll for open requests every ``period`` [s] in a daemon thread."""

        def loop() -> None:
            while True:
                time.sleep(period)
                self.poll_open_request()

        threading.Thread(target=loop, name="studio-open-requests", daemon=True).start()
