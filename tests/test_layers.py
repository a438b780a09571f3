"""hamid's imports run one way: no cycle among its modules (lazy imports inside functions
count too), the chunked fit does not reach back into the API, and no module takes a
private name (_x) from another. Also the sizes that keep the house easy to change."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).parent.parent / "hamid"
MODULES = {path.stem: path for path in PACKAGE.glob("*.py") if path.stem != "__init__"}


def _imports(name: str) -> tuple[set[str], list[str]]:
    """The hamid modules `name` imports, and the private names it takes from them."""
    tree = ast.parse(MODULES[name].read_text())
    found, private, aliases = set(), [], {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("hamid"):
            parts = node.module.split(".")
            if len(parts) > 1:          # from hamid.x import y
                found.add(parts[1])
                private += [f"{parts[1]}.{a.name}" for a in node.names
                            if a.name.startswith("_") and not a.name.startswith("__")]
            else:                       # from hamid import x, y
                for a in node.names:
                    if a.name in MODULES:
                        found.add(a.name)
                        aliases[a.asname or a.name] = a.name
        elif isinstance(node, ast.Import):
            for a in node.names:
                parts = a.name.split(".")
                if parts[0] == "hamid" and len(parts) > 1:
                    found.add(parts[1])
                    aliases[a.asname or a.name] = parts[1]
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                and aliases.get(node.value.id, name) != name
                and node.attr.startswith("_") and not node.attr.startswith("__")):
            private.append(f"{aliases[node.value.id]}.{node.attr}")
    found.discard(name)
    return found & set(MODULES), private


GRAPH = {name: _imports(name)[0] for name in MODULES}


def _cycle() -> list[str] | None:
    """One cycle of the import graph, or None (depth-first search with colours)."""
    state: dict[str, int] = {}   # 1: on the path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(GRAPH[node]):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        path.pop()
        state[node] = 2
        return None

    for node in sorted(GRAPH):
        if node not in state and (found := visit(node)):
            return found
    return None


def test_the_import_graph_has_no_cycle():
    assert _cycle() is None, " -> ".join(_cycle() or [])


def test_the_cycle_finder_finds_a_cycle(monkeypatch):
    """The check above can fail: a graph with a cycle is reported."""
    monkeypatch.setitem(GRAPH, "errors", {"api"})
    assert _cycle() is not None


def test_the_chunked_fit_does_not_import_the_api():
    assert "api" not in GRAPH["stream"]
    # nor anything that imports the API
    assert not {name for name, deps in GRAPH.items() if "api" in deps} & GRAPH["stream"]


@pytest.mark.parametrize("name", sorted(MODULES))
def test_no_private_name_is_taken_from_another_module(name):
    assert _imports(name)[1] == []


@pytest.mark.parametrize("name", sorted(MODULES))
def test_modules_stay_small(name):
    lines = len(MODULES[name].read_text().splitlines())
    assert lines <= (250 if name == "api" else 800), f"{name}.py has {lines} lines"


def test_the_time_units_the_options_offer_are_those_the_reader_converts():
    """options.py lists them without importing naming.py (the CLI imports options)."""
    from hamid import naming, options

    assert tuple(naming.TIME_UNITS) == options.TIME_UNITS
