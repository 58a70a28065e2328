"""The package's layers: each subpackage imports only from its own layer and the ones below.

base (errors, paths, constants, storage) < physics < robot < toss < planning < sim < serve
< library < optimize < ui < cli. The core (everything below ui) never imports the GUI
libraries. Imports inside ``if TYPE_CHECKING:`` blocks are annotations only and not
counted; ``studio/__init__.py`` (the public API, loaded lazily) is the one exception.
No function or method in the package is longer than 80 lines.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "studio"
LAYERS = ["base", "physics", "robot", "toss", "planning", "sim", "serve", "library", "optimize", "ui", "cli"]
BASE_MODULES = {"errors", "paths", "constants", "storage"}
GUI_LIBRARIES = {"viser", "panel", "bokeh", "holoviews", "matplotlib"}


def _layer(module: str) -> str:
    """Layer of a dotted ``studio...`` module name."""
    parts = module.split(".")
    if len(parts) == 1:
        return "base"
    head = parts[1]
    if head in BASE_MODULES:
        return "base"
    if head == "cli":
        return "cli"
    assert head in LAYERS, f"{module}: not in a known layer"
    return head


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imports(tree: ast.AST, module: str) -> list[tuple[str, int]]:
    """(imported module, line) of every runtime import in ``tree``."""
    found: list[tuple[str, int]] = []

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _is_type_checking(node):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            found.extend((alias.name, node.lineno) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the importing package
                base = module.split(".")[: -node.level] if not module.endswith("__init__") else module.split(".")
                name = ".".join([*base, node.module] if node.module else base)
            else:
                name = node.module or ""
            found.append((name, node.lineno))
            if name == "studio":  # from studio import errors, constants, ...
                found.extend((f"studio.{alias.name}", node.lineno) for alias in node.names)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return found


SOURCES = sorted(p for p in PACKAGE.rglob("*.py") if p.name != "__init__.py" or p.parent != PACKAGE)


def test_the_folder_tree_names_the_layers() -> None:
    subpackages = {p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert subpackages == set(LAYERS[1:-1]) | {"storage"}
    top = {p.stem for p in PACKAGE.glob("*.py")}
    assert top == {"__init__", "cli", "errors", "paths", "constants"}


@pytest.mark.parametrize("path", SOURCES, ids=[_module_name(p) for p in SOURCES])
def test_imports_go_down_the_layers(path: Path) -> None:
    module = _module_name(path)
    own = LAYERS.index(_layer(module))
    tree = ast.parse(path.read_text(encoding="utf-8"))
    for name, line in _imports(tree, module):
        if name.startswith("studio.") or name == "studio":
            if name == "studio":
                continue
            assert LAYERS.index(_layer(name)) <= own, f"{module}:{line} imports {name} from a higher layer ({_layer(name)} > {_layer(module)})"
        elif own < LAYERS.index("ui"):
            assert name.split(".")[0] not in GUI_LIBRARIES, f"{module}:{line}: the core imports the GUI library {name}"


def test_the_checker_sees_a_violation(tmp_path: Path) -> None:
    """The test above can fail: an upward and a GUI import are both found."""
    tree = ast.parse("import viser\nif TYPE_CHECKING:\n    from studio.ui.app import X\ndef f():\n    from studio.ui.scene import Y\n")
    names = [n for n, _ in _imports(tree, "studio.physics.ball")]
    assert names == ["viser", "studio.ui.scene"]
    assert LAYERS.index(_layer("studio.ui.scene")) > LAYERS.index(_layer("studio.physics.ball"))


MAX_FUNCTION_LINES = 80
"""Longest function or method in ``studio/`` (``def`` line to last line, decorators not counted)."""
LONG_FUNCTIONS_ALLOWED: frozenset[str] = frozenset()
"""``module:qualified name`` of longer functions that are declarative tables (none today)."""


def _functions(tree: ast.AST) -> list[tuple[str, int]]:
    """(qualified name, lines) of every function and method in ``tree``, nested ones included."""
    found: list[tuple[str, int]] = []

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                name = f"{prefix}{child.name}"
                found.append((name, (child.end_lineno or child.lineno) - child.lineno + 1))
                visit(child, f"{name}.")
            elif isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}{child.name}.")
            else:
                visit(child, prefix)

    visit(tree, "")
    return found


@pytest.mark.parametrize("path", SOURCES, ids=[_module_name(p) for p in SOURCES])
def test_no_function_is_longer_than_80_lines(path: Path) -> None:
    module = _module_name(path)
    tree = ast.parse(path.read_text(encoding="utf-8"))
    long = {
        f"{module}:{name}": n
        for name, n in _functions(tree)
        if n > MAX_FUNCTION_LINES and f"{module}:{name}" not in LONG_FUNCTIONS_ALLOWED
    }
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines (cut them into named pieces): {long}"


def test_the_length_check_sees_a_long_method() -> None:
    body = "\n".join(f"        x{i} = {i}" for i in range(80))
    tree = ast.parse(f"class A:\n    def short(self):\n        pass\n\n    def long(self):\n{body}\n")
    assert dict(_functions(tree)) == {"A.short": 2, "A.long": 81}
