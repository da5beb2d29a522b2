"""The layout of server/ (issue 29): no import cycles between its modules, and the gallery's storage imports nothing
that draws or drives a session.

The imports are read from the source with ast (nothing is imported), including the ones inside functions: a lazy
import hides a cycle from the interpreter but not from the reader, and tomorrow's refactor may hoist it. Imports
under `if TYPE_CHECKING:` (annotations only, never run) are left out of the cycle check, except for the scheduler,
which must not name the session at all: it works through the Playable protocol.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SERVER = ROOT / "server"
# What draws or drives a session: the gallery's storage must reach none of these, even through another module.
SESSION_SIDE = ("server.play", "server.agents", "server.recordings", "server.editor", "server.drafts", "server.bench",
                "server.app", "viser")
# The gallery package's storage part: everything in server/gallery (its tab part lives in server/play/gallery_tab.py).
GALLERY = "server.gallery"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def server_modules() -> dict[str, Path]:
    return {module_name(path): path for path in SERVER.rglob("*.py")}


def _type_checking_blocks(tree: ast.AST) -> set[int]:
    """ids of the import nodes inside `if TYPE_CHECKING:` blocks."""
    inside: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            inside.update(id(child) for stmt in node.body for child in ast.walk(stmt))
    return inside


def imports_of(path: Path, name: str, known: set[str], typing: bool = False) -> set[str]:
    """Every module `name` imports (resolved to a module of `known` where the target is one, else the name given);
    with `typing`, also the imports made for annotations only (under `if TYPE_CHECKING:`)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    skip = set() if typing else _type_checking_blocks(tree)
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            for alias in node.names:
                candidate = f"{base}.{alias.name}"
                found.add(candidate if candidate in known else base)
    return found


def import_graph(typing: bool = False) -> dict[str, set[str]]:
    modules = server_modules()
    known = set(modules)
    return {name: imports_of(path, name, known, typing) for name, path in modules.items()}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle among the graph's own nodes (as a path that starts and ends at the same module), or None."""
    WHITE, GREY, BLACK = 0, 1, 2
    colour = dict.fromkeys(graph, WHITE)
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        colour[node] = GREY
        stack.append(node)
        for target in sorted(graph[node]):
            if target not in graph:
                continue
            if colour[target] == GREY:
                return stack[stack.index(target):] + [target]
            if colour[target] == WHITE and (cycle := visit(target)):
                return cycle
        stack.pop()
        colour[node] = BLACK
        return None

    for node in sorted(graph):
        if colour[node] == WHITE and (cycle := visit(node)):
            return cycle
    return None


def reachable(graph: dict[str, set[str]], start: str) -> set[str]:
    seen: set[str] = set()
    todo = [start]
    while todo:
        node = todo.pop()
        for target in graph.get(node, ()):
            if target not in seen:
                seen.add(target)
                todo.append(target)
    return seen


def test_the_cycle_finder_finds_a_cycle_and_accepts_a_tree():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b", "c"}, "b": {"c", "os"}, "c": set()}) is None


def test_imports_are_read_from_the_source():
    graph = import_graph()
    assert "server.play.draw" in graph["server.play.session"]
    assert "server.play.scheduler" in graph["server.play.session"]
    assert "server.play.steps" in graph["server.play.warmup"]  # a lazy `from server.play import steps`, resolved
    assert "server.play.manager" not in import_graph(typing=True)["server.play.session"]  # SessionHost instead
    assert "server.play.session" in graph["server.play.manager"]


def test_no_import_cycle_in_server():
    cycle = find_cycle(import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])


def test_no_import_cycle_in_server_play_even_for_annotations():
    """The session's parts (buttons, editing, hooks, loop, manager) each name the narrow protocol they need instead
    of importing the session that imports them (issue 37): no cycle, TYPE_CHECKING imports included."""
    graph = import_graph(typing=True)
    play = {name: targets for name, targets in graph.items() if name.startswith("server.play")}
    cycle = find_cycle(play)
    assert cycle is None, "import cycle in server/play: " + " -> ".join(cycle or [])


def package_graph(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """The import graph between server's packages (server.play, server.recordings, ...)."""
    def package(name: str) -> str:
        return ".".join(name.split(".")[:2])

    packages: dict[str, set[str]] = {}
    for name, targets in graph.items():
        packages.setdefault(package(name), set()).update(
            package(t) for t in targets if t.startswith("server.") and package(t) != package(name))
    return packages


def test_no_import_cycle_between_server_packages():
    """One of two packages owns their link: e.g. recordings build on play, so play never imports recordings (the
    gallery tab gets its replay function from server.app)."""
    packages = package_graph(import_graph(typing=True))
    assert "server.play" in packages["server.recordings"]
    cycle = find_cycle(packages)
    assert cycle is None, "import cycle between packages: " + " -> ".join(cycle or [])


def test_the_scheduler_does_not_import_the_session():
    assert "server.play.session" not in reachable(import_graph(typing=True), "server.play.scheduler")


def test_gallery_storage_reaches_nothing_that_draws_or_drives_a_session():
    graph = import_graph()
    storage = [name for name in graph if name == GALLERY or name.startswith(GALLERY + ".")]
    assert {"server.gallery.store", "server.gallery.api", "server.gallery.runs", "server.gallery.migrations",
            "server.gallery.limits", "server.gallery.proof", "server.gallery.agents"} <= set(storage)
    for name in storage:
        bad = sorted(target for target in reachable(graph, name) | {name}
                     if any(target == side or target.startswith(side + ".") for side in SESSION_SIDE))
        assert not bad, f"{name} reaches {bad}"
