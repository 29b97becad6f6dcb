"""The import graph of the project's packages: no cycles, and imports only down the layers.

The graph is read from the source with `ast`, every import statement counted wherever it stands
(inside a function, under `TYPE_CHECKING`): an import moved into a function still runs, so a
cycle it closes is still a cycle, only a later one, and a layer it crosses is still crossed.
The layers are docs/architecture.md's ("Checking the layers").
"""

from __future__ import annotations

import ast
import re
from collections.abc import Iterable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = (
    "protocol",
    "structures",
    "timewarp",
    "simulation_adapters",
    "server",
    "scalesteer",
    "thesis",
)

BELOW = {"protocol", "structures"}
"""What the server and the adapters both stand on: the wire format and the file readers."""
SERVER = {"server.render", "server.pipeline", "server.session", "server.web"}
MAY_IMPORT: dict[str, set[str]] = {
    "protocol": set(),
    "structures": {"protocol"},
    "timewarp": set(),
    "simulation_adapters": BELOW,
    "scalesteer": BELOW | {"simulation_adapters"},  # the Python client, where it is present
    "server": BELOW,  # the server-wide modules: settings, metrics, heap, supervisor
    "server.render": BELOW | {"timewarp", "server"},
    "server.pipeline": BELOW | {"timewarp", "server", "server.render"},
    "server.session": BELOW | {"timewarp", "server", "server.render", "server.pipeline"},
    "server.web": BELOW | {"timewarp", "server"} | SERVER - {"server.web"},
    # the composition root: the command line wires servers and adapters together
    "server.commands": BELOW | {"timewarp", "server", "simulation_adapters"} | SERVER,
    "thesis": BELOW | {"timewarp", "server.render"},
}
"""Layer -> the layers it may import besides its own. Arrows point down the data flow: the
server never imports the adapters, except its command line, which starts both."""


def layer(module: str) -> str:
    """The layer a module belongs to: its top-level package, or for `server` its sub-package
    (`server.web`, ...; the modules directly in `server/` are the server-wide layer)."""
    top, _, rest = module.partition(".")
    if top == "server" and rest:
        sub = f"server.{rest.partition('.')[0]}"
        return sub if sub in MAY_IMPORT else "server"
    return top


def modules(root: Path, packages: Iterable[str] = PACKAGES) -> dict[str, Path]:
    """Dotted module name -> source file, for every module of `packages` under `root`."""
    out: dict[str, Path] = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = path
    return out


def _known(name: str, known: dict[str, Path]) -> str | None:
    """The project module `name` names (a name imported from a module: that module)."""
    while name and name not in known:
        name = name.rpartition(".")[0]
    return name or None


def import_graph(known: dict[str, Path]) -> dict[str, set[str]]:
    """Module -> the project modules its import statements name, all of them counted."""
    graph: dict[str, set[str]] = {}
    for module, path in known.items():
        named: set[str] = set()
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                named |= {t for a in node.names if (t := _known(a.name, known))}
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                    base = ".".join([*up, *([node.module] if node.module else [])])
                named |= {t for a in node.names if (t := _known(f"{base}.{a.name}", known))}
        named.discard(module)
        graph[module] = named
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Each import cycle, as the modules along it back to the first (one per strongly connected
    set of modules)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = set()
            while True:
                w = stack.pop()
                group.add(w)
                if w == v:
                    break
            if len(group) > 1:
                found.append(_path_through(graph, group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def _path_through(graph: dict[str, set[str]], group: set[str]) -> list[str]:
    """A shortest cycle inside `group`, from its first module back to it."""
    start = min(group)
    paths = {start: [start]}
    frontier = [start]
    while frontier:
        nxt = []
        for v in frontier:
            for w in sorted(graph[v] & group):
                if w == start:
                    return [*paths[v], start]
                if w not in paths:
                    paths[w] = [*paths[v], w]
                    nxt.append(w)
        frontier = nxt
    raise AssertionError(f"no cycle through {start}")


def test_no_import_cycles() -> None:
    found = cycles(import_graph(modules(ROOT)))
    assert not found, "import cycles: " + "; ".join(" -> ".join(c) for c in found)


def crossings(graph: dict[str, set[str]]) -> list[str]:
    """Each import of a layer its importer may not import, said in words."""
    out = []
    for module in sorted(graph):
        allowed = MAY_IMPORT[layer(module)]
        for target in sorted(graph[module]):
            if layer(target) != layer(module) and layer(target) not in allowed:
                out.append(
                    f"{module} imports {target} ({layer(module)} may import {sorted(allowed)})"
                )
    return out


def test_imports_point_down_the_layers() -> None:
    graph = import_graph(modules(ROOT))
    assert set(map(layer, graph)) <= set(MAY_IMPORT), "a package without a layer"
    assert not crossings(graph), "\n".join(crossings(graph))


def path_edits(path: Path) -> list[int]:
    """Lines of `path` that change the interpreter's import path (`sys.path` mutated or
    assigned, `site.addsitedir`)."""
    lines = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        target: ast.expr | None = None
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            target = node.func.value
            if ast.unparse(node.func) == "site.addsitedir":
                lines.append(node.lineno)
        elif isinstance(node, ast.Assign | ast.AugAssign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            for t in targets:
                target = t.value if isinstance(t, ast.Subscript) else t
                if ast.unparse(target) == "sys.path":
                    lines.append(node.lineno)
            continue
        if target is not None and ast.unparse(target) == "sys.path":
            lines.append(node.lineno)
    return sorted(lines)


def test_no_shipped_code_edits_the_import_path() -> None:
    """An edited `sys.path` makes every folder beside it importable and shadows what is
    installed; the packages import as installed (or from a checkout with `PYTHONPATH=.`)."""
    edits = [
        f"{path.relative_to(ROOT)}:{line}"
        for path in modules(ROOT).values()
        for line in path_edits(path)
    ]
    assert not edits, f"sys.path edited at {', '.join(edits)}"


def test_a_cycle_closed_inside_a_function_is_found(tmp_path: Path) -> None:
    pkg = tmp_path / "protocol"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from protocol.b import B\nA = 1\n")
    (pkg / "b.py").write_text("B = 2\n\ndef late():\n    from protocol import a\n    return a\n")
    (pkg / "c.py").write_text("from . import a\n")
    graph = import_graph(modules(tmp_path, ["protocol"]))
    assert graph["protocol.c"] == {"protocol.a"}
    assert cycles(graph) == [["protocol.a", "protocol.b", "protocol.a"]]


def test_an_import_against_the_layers_is_named(tmp_path: Path) -> None:
    for folder in ("server/web", "simulation_adapters"):
        (tmp_path / folder).mkdir(parents=True)
        (tmp_path / folder / "__init__.py").write_text("")
    (tmp_path / "server/__init__.py").write_text("")
    (tmp_path / "simulation_adapters/replay.py").write_text("")
    (tmp_path / "server/web/children.py").write_text(
        "def start():\n    from simulation_adapters import replay\n"
    )
    graph = import_graph(modules(tmp_path, ["server", "simulation_adapters"]))
    assert crossings(graph) == [
        "server.web.children imports simulation_adapters.replay (server.web may import "
        "['protocol', 'server', 'server.pipeline', 'server.render', 'server.session', "
        "'structures', 'timewarp'])"
    ]


def test_an_import_path_edit_is_found(tmp_path: Path) -> None:
    source = tmp_path / "m.py"
    source.write_text(
        "import site, sys\n"
        "sys.path.insert(0, '.')\n"
        "sys.path += ['x']\n"
        "sys.path[:0] = ['y']\n"
        "site.addsitedir('z')\n"
        "print(sys.path[0])\n"
    )
    assert path_edits(source) == [2, 3, 4, 5]


def documented_layers(text: str) -> dict[str, set[str]]:
    """docs/architecture.md's table of layers: layer -> what the table says it may import."""
    section = text.split("## Checking the layers", 1)[1]
    table: dict[str, set[str]] = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 2 or not cells[0].startswith("`"):
            continue
        names = set(re.findall(r"`([\w.]+)`", cells[1]))
        if "all of `server`" in cells[1]:
            names |= SERVER | {"server"}
        for layer_name in re.findall(r"`([\w.]+)`", cells[0]):
            table[layer_name] = names
    return table


def test_the_documented_layers_are_the_checked_ones() -> None:
    """The table a reader sees is the one this file enforces, row for row."""
    text = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    assert documented_layers(text) == MAY_IMPORT
