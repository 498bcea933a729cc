"""The package's import graph: no module imports itself back through others (lint-imports checks
the layering contracts in pyproject.toml; this checks what contracts cannot: cycles anywhere)."""

import grimp


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in edges:
        if v not in index:
            visit(v)
    return found


def test_the_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_cycle_in_the_package():
    graph = grimp.build_graph("pancam_graph", exclude_type_checking_imports=False)
    modules = set(graph.modules)
    assert len(modules) > 50
    edges = {m: set(graph.find_modules_directly_imported_by(m)) & modules for m in modules}
    assert _cycles(edges) == []


def test_every_module_of_the_package_sits_in_a_layer():
    import pkgutil
    import tomllib
    from pathlib import Path

    import pancam_graph

    pyproject = tomllib.loads((Path(pancam_graph.__file__).parents[1] / "pyproject.toml").read_text())
    layers = pyproject["tool"]["importlinter"]["contracts"][0]["layers"]
    layered = {name.strip().removeprefix("pancam_graph.") for layer in layers for name in layer.split("|")}
    data = {"scenarios"}  # the bundled scenario files: no code
    top_level = {m.name for m in pkgutil.iter_modules(pancam_graph.__path__)} - {"__main__"} - data
    assert top_level - layered == set()
