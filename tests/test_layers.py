"""hamid's imports run one way, step by step (docs/architecture.md): each subpackage imports
only the steps before it, no module takes a private name (_x) from another, there is no
cycle (lazy imports inside functions count too), and the sizes that keep the house easy
to change hold."""

from __future__ import annotations

import ast
import dataclasses
import importlib
import inspect
from pathlib import Path

import pytest

PACKAGE = Path(__file__).parent.parent / "hamid"


def _dotted(path: Path) -> str:
    """`linear.solve` for hamid/linear/solve.py, `cli` for hamid/cli/__init__.py."""
    parts = list(path.relative_to(PACKAGE).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts) or "__init__"


MODULES = {_dotted(path): path for path in PACKAGE.rglob("*.py")}
SUBPACKAGES = sorted(path.parent.name for path in PACKAGE.glob("*/__init__.py"))

# The steps, in the order data flow through a fit: each imports only those before it.
ORDER = ("errors", "__init__", "safe_text", "read_limits", "executor", "options", "model", "data",
         "linear", "refine", "backbone", "result", "report", "prediction", "plot", "signals",
         "simulation", "api", "selection", "batch", "cli")

# Imports against the order, each with its reason. Every one is a debt to pay, not a rule:
# the test fails when one is no longer there, so that the list only shrinks.
AGAINST_THE_ORDER = {
    # a model file is a TOML document, read by the bounded readers of data/
    ("model.models", "data.documents"),
    # the reading options are checked where they are made, against the readers' own tables
    ("options", "data.text_layout"),
    ("options", "data.input_size"),
    # each trajectory's period and time step, found as the file is loaded, by the same
    # function the windows of the weak form are sized with
    ("data.loading", "linear.design"),
    # FitResult's conveniences: .summary()/.to_html(), .plot(), .simulate()
    ("result.fit_result", "report.formats"),
    ("result.fit_result", "plot.figures"),
    ("result.fit_result", "simulation"),
    # .predict(): the fitted model over a recording, the records read as the fit read them
    ("result.fit_result", "prediction"),
}


def _layer(module: str) -> str:
    return module.split(".")[0]


def _imports(name: str) -> tuple[set[str], list[str]]:
    """The hamid modules `name` imports, and the private names it takes from them."""
    path = MODULES[name]
    tree = ast.parse(path.read_text())
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found, private, aliases = set(), [], {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = ".".join(package.split(".")[:len(package.split(".")) - node.level + 1])
                target = ".".join(p for p in (base, node.module) if p)
            elif node.module and node.module.startswith("hamid"):
                target = node.module.removeprefix("hamid").lstrip(".")
            else:
                continue
            for a in node.names:
                sub = f"{target}.{a.name}" if target else a.name
                if sub in MODULES:                   # a module imported by name
                    found.add(sub)
                    aliases[a.asname or a.name] = sub
                else:
                    found.add(target or "__init__")
                    if a.name.startswith("_") and not a.name.startswith("__"):
                        private.append(f"{target}.{a.name}")
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("hamid."):
                    found.add(a.name.removeprefix("hamid."))
                    if a.asname:
                        aliases[a.asname] = a.name.removeprefix("hamid.")
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                and aliases.get(node.value.id, name) != name
                and node.attr.startswith("_") and not node.attr.startswith("__")):
            private.append(f"{aliases[node.value.id]}.{node.attr}")
    found.discard(name)
    return found & set(MODULES), private


GRAPH = {name: _imports(name)[0] for name in MODULES}


def _against_the_order(graph: dict[str, set[str]]) -> set[tuple[str, str]]:
    return {(name, dep) for name, deps in graph.items() for dep in deps
            if ORDER.index(_layer(dep)) > ORDER.index(_layer(name))}


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


def test_every_module_belongs_to_a_step():
    assert {_layer(name) for name in MODULES} <= set(ORDER)


def test_each_step_imports_only_the_steps_before_it():
    assert _against_the_order(GRAPH) == AGAINST_THE_ORDER


def test_an_import_against_the_order_is_found(monkeypatch):
    """The check above can fail: the estimator reaching for the report is reported."""
    monkeypatch.setitem(GRAPH, "linear.estimate", GRAPH["linear.estimate"] | {"report.formats"})
    assert ("linear.estimate", "report.formats") in _against_the_order(GRAPH)


def test_the_model_imports_nothing_of_hamid_but_errors():
    for name in (n for n in MODULES if _layer(n) == "model"):
        outside = {dep for dep in GRAPH[name] if _layer(dep) != "model"} - {"errors"}
        assert outside <= {dep for importer, dep in AGAINST_THE_ORDER if importer == name}


def test_reports_and_figures_never_reach_the_estimators():
    """report/ reads results; plot/ redraws the fitted model from its records with the same
    rows and integrator, never fitting: neither imports the fit of rows or trajectories."""
    for name in (n for n in MODULES if _layer(n) in ("report", "plot")):
        assert not {d for d in GRAPH[name]
                    if d in ("linear.estimate", "linear.chunked", "refine.joint_refinement")}


def test_the_estimators_know_nothing_of_what_comes_after():
    later = {"result", "report", "plot", "selection", "batch", "api", "cli"}
    for name in (n for n in MODULES if _layer(n) in ("linear", "refine")):
        assert not {_layer(d) for d in GRAPH[name]} & later, name


def test_only_the_command_line_imports_click():
    for name, path in MODULES.items():
        tree = ast.parse(path.read_text())
        uses = {a.name.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.Import)
                for a in node.names}
        uses |= {node.module.split(".")[0] for node in ast.walk(tree)
                 if isinstance(node, ast.ImportFrom) and node.module and not node.level}
        assert "click" not in uses or _layer(name) == "cli", name


def test_the_import_graph_has_no_cycle():
    assert _cycle() is None, " -> ".join(_cycle() or [])


def test_the_cycle_finder_finds_a_cycle(monkeypatch):
    """The check above can fail: a graph with a cycle is reported."""
    monkeypatch.setitem(GRAPH, "errors", {"api"})
    assert _cycle() is not None


@pytest.mark.parametrize("name", sorted(MODULES))
def test_no_private_name_is_taken_from_another_module(name):
    assert _imports(name)[1] == []


@pytest.mark.parametrize("name", sorted(MODULES))
def test_modules_stay_small(name):
    lines = len(MODULES[name].read_text().splitlines())
    assert lines <= (250 if name == "api" else 800), f"{MODULES[name]} has {lines} lines"


def test_the_package_is_in_subpackages_by_step():
    top = [name for name in MODULES if "." not in name and name not in SUBPACKAGES]
    assert len(top) <= 12, top
    assert len(SUBPACKAGES) >= 5
    for package in SUBPACKAGES:
        inside = [name for name in MODULES if name.startswith(package + ".")]
        assert 1 <= len(inside) <= 12, (package, inside)
        assert ast.get_docstring(ast.parse(MODULES[package].read_text())), package


def test_no_module_is_named_after_the_standard_library():
    import sys

    for name in MODULES:
        assert name.rsplit(".", 1)[-1] not in sys.stdlib_module_names, name


def test_the_time_units_the_options_offer_are_those_the_reader_converts():
    """options.py lists them without importing the column roles (the CLI imports options)."""
    from hamid import options
    from hamid.data import column_roles

    assert tuple(column_roles.TIME_UNITS) == options.TIME_UNITS


# A call passes at most this many arguments by position: beyond it, by keyword, so that
# the steps hand their work over by name (a swapped pair of 13 positional arguments ran).
MOST_POSITIONAL = 6


def _long_positional_calls(source: str) -> list[int]:
    """The lines of calls in `source` that pass over MOST_POSITIONAL arguments by
    position (a starred argument, of however many, not counted)."""
    return [node.lineno for node in ast.walk(ast.parse(source))
            if isinstance(node, ast.Call)
            and sum(not isinstance(a, ast.Starred) for a in node.args) > MOST_POSITIONAL]


def test_no_call_passes_more_than_six_arguments_by_position():
    found = [f"{path.relative_to(PACKAGE.parent)}:{line}"
             for path in sorted(PACKAGE.rglob("*.py"))
             for line in _long_positional_calls(path.read_text())]
    assert found == []


def test_a_call_of_seven_positional_arguments_is_found():
    source = ("f(1, 2, 3, 4, 5, 6)\ng(1, 2, 3, 4, 5, 6, 7)\nh(1, 2, 3, 4, 5, 6, *rest)\n"
              "k(a, b, c, d, e, f, g=7)\nm(1, 2, 3, 4, 5, n(1, 2, 3, 4, 5, 6, 7))\n")
    assert _long_positional_calls(source) == [2, 5]


def _step(dotted: str) -> object:
    module, name = dotted.rsplit(".", 1)
    return getattr(importlib.import_module(f"hamid.{module}"), name)


@pytest.mark.parametrize("step", ["linear.estimate.LinearFit", "refine.outcome.Outcome",
                                  "selection.best_subsets.Ranking",
                                  "selection.best_subsets.Candidate",
                                  "selection.select_terms.Choice"])
def test_the_steps_hand_over_keyword_only_dataclasses(step):
    kind = _step(step)
    assert dataclasses.fields(kind)
    assert all(field.kw_only for field in dataclasses.fields(kind))


@pytest.mark.parametrize("step", ["refine.joint_refinement.refine"])
def test_the_steps_take_their_inputs_by_keyword(step):
    parameters = inspect.signature(_step(step)).parameters.values()
    assert parameters
    assert all(p.kind == inspect.Parameter.KEYWORD_ONLY for p in parameters)
