"""jax2d's module structure (issue 35): no import cycle among its modules, no private name imported across them,
and step.py short enough to read as the pipeline it is."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[2] / "jax2d"
STEP_MAX_LINES = 400


def _imports(name: str, source: str, modules: set[str]) -> tuple[set[str], list[str]]:
    """The jax2d modules `name` imports (anywhere in the file, late imports too) and its uses of another jax2d
    module's private names: `from jax2d.x import _y` and `x._y` on a module imported as x."""
    imported, private, aliases = set(), [], {}
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module == "jax2d":
                for alias in node.names:
                    if alias.name in modules:  # from jax2d import broad_phase
                        imported.add(alias.name)
                        aliases[alias.asname or alias.name] = alias.name
                    else:  # from jax2d import SimState: the package itself
                        imported.add("__init__")
                        if alias.name.startswith("_"):
                            private.append(f"{name}: from jax2d import {alias.name}")
            elif node.module.startswith("jax2d."):
                target = node.module.split(".")[1]
                imported.add(target)
                private += [f"{name}: from {node.module} import {alias.name}" for alias in node.names
                            if alias.name.startswith("_")]
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("jax2d."):
                    target = alias.name.split(".")[1]
                    imported.add(target)
                    if alias.asname:
                        aliases[alias.asname] = target
                elif alias.name == "jax2d":
                    imported.add("__init__")
    for node in ast.walk(ast.parse(source)):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases
                and node.attr.startswith("_") and not node.attr.startswith("__")):
            private.append(f"{name}: {node.value.id}.{node.attr}")
    imported.discard(name)
    return imported, private


def check(sources: dict[str, str]) -> tuple[list[list[str]], list[str]]:
    """(import cycles, private cross-module uses) among modules given as {name: source}; "__init__" is the
    package. A cycle is listed as the modules along it, its first module repeated at the end."""
    modules = set(sources) - {"__init__"}
    graph, private = {}, []
    for name, source in sources.items():
        graph[name], found = _imports(name, source, modules)
        private += found
    cycles, state = [], {}  # state: 1 on the current path, 2 done

    def visit(node, path):
        state[node] = 1
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                cycles.append(path[path.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, path + [nxt])
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])
    return cycles, private


def _package_sources() -> dict[str, str]:
    return {p.stem: p.read_text() for p in sorted(PACKAGE.glob("*.py"))}


def test_jax2d_has_no_import_cycle_and_imports_no_private_name_across_modules():
    cycles, private = check(_package_sources())
    assert not cycles, f"import cycles among jax2d modules: {cycles}"
    assert not private, f"private names used across jax2d modules: {private}"


def test_the_check_finds_a_late_import_cycle_and_private_names():
    """The checker itself, on made-up modules: a cycle hidden by a function-level import, and both ways of
    reaching a private name."""
    sources = {
        "__init__": "from jax2d.a import run\n",
        "a": "from jax2d import b\n\ndef run():\n    return b._helper()\n",
        "b": "def _helper():\n    from jax2d.a import run\n    from jax2d.c import _ROW\n    return run, _ROW\n",
        "c": "_ROW = 1\n",
    }
    cycles, private = check(sources)
    assert ["a", "b", "a"] in cycles
    assert sorted(private) == ["a: b._helper", "b: from jax2d.c import _ROW"]
    assert check({"__init__": "from jax2d.a import x\n", "a": "x = 1\n"}) == ([], [])


def test_step_reads_as_the_pipeline_in_at_most_400_lines():
    lines = len((PACKAGE / "step.py").read_text().splitlines())
    assert lines <= STEP_MAX_LINES, f"jax2d/step.py has {lines} lines: move a stage's details into its module"


def test_each_stage_of_the_compiled_step_carries_its_named_scope():
    """A profile attributes kernels to stages through the compiled program's op names (step.py's docstring)."""
    import re

    import jax.numpy as jnp

    import jax2d

    capacity = jax2d.Capacity(polygons=3, circles=1, joints=1, thrusters=1, max_vertices=4)
    state = jax2d.empty_state(capacity)
    text = jax2d.jit(jax2d.step).lower(state, jax2d.SimParams(), jnp.zeros(1), jnp.zeros(1)).compile().as_text()
    scopes = set(re.findall(r"jax2d_[a-z_]+", text))
    assert {"jax2d_narrow_phase", "jax2d_prepare", "jax2d_substeps", "jax2d_restitution", "jax2d_joint_projection",
            "jax2d_static_walls", "jax2d_store"} <= scopes, scopes
