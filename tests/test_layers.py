"""The package's layers, read from DESIGN.md's table, against every import in the code (read with ast)."""

from __future__ import annotations

import ast
import re
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: the installed name of each source folder
FOLDERS = {"appliance": "appliance", "calibration": "viper_calibration"}


@dataclass(frozen=True)
class Import:
    source: str  # the importing module
    target: str  # the imported module, resolved as far as the code names it
    line: int
    deferred: bool  # inside a function
    commented: bool  # a comment on its line or the line above


def layer_table() -> tuple[dict[str, str], dict[str, set[str]]]:
    """DESIGN.md's "Layers" table: the layer of each module or package, and the layers each may import."""
    text = (REPO / "DESIGN.md").read_text(encoding="utf-8")
    section = text.split("## Layers", 1)[1].split("\n## ", 1)[0]
    layer_of: dict[str, str] = {}
    may: dict[str, set[str]] = {}
    for row in re.findall(r"^\|(.+)\|$", section, flags=re.M):
        cells = [c.strip() for c in row.split("|")]
        if len(cells) != 3 or cells[0] in ("Layer", "") or set(cells[0]) <= {"-"}:
            continue
        name, modules, allowed = cells
        for module in re.findall(r"`([\w.]+)`", modules):
            layer_of[module] = name
        may[name] = {a.strip() for a in allowed.split(",")} | {name}
    return layer_of, may


def module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    parts[0] = FOLDERS[parts[0]]
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def source_files() -> list[Path]:
    return sorted(p for folder in FOLDERS for p in (REPO / folder).rglob("*.py"))


def _commented(lines: list[str], lineno: int) -> bool:
    """A comment on the import's line, or above the block of imports it belongs to."""
    if "#" in lines[lineno - 1]:
        return True
    i = lineno - 2
    while i >= 0 and (lines[i].strip().startswith(("from ", "import ")) or lines[i].rstrip().endswith((",", "("))
                      or lines[i].strip() in (")", "")):
        i -= 1
    return i >= 0 and lines[i].strip().startswith("#")


def imports_of(path: Path, modules: set[str]) -> list[Import]:
    """The package-internal imports of one file (``from a import b`` counts as ``a.b`` where b is a module)."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    text = path.read_text(encoding="utf-8")
    lines = text.splitlines()
    tree = ast.parse(text)
    deferred_nodes = {id(n) for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
                      for n in ast.walk(f) if isinstance(n, (ast.Import, ast.ImportFrom))}
    out = []
    for node in ast.walk(tree):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            targets = [f"{module}.{a.name}" if f"{module}.{a.name}" in modules else module for a in node.names]
        for target in targets:
            if target.split(".")[0] in FOLDERS.values():
                out.append(Import(name, target, node.lineno, id(node) in deferred_nodes,
                                  _commented(lines, node.lineno)))
    return out


def layer(module: str, layer_of: dict[str, str]) -> str | None:
    """The layer of a module: its own entry, or its package's (``appliance.estimator.search`` -> estimator)."""
    parts = module.split(".")
    if parts[0] == "viper_calibration":
        return layer_of.get("viper_calibration")
    if len(parts) < 2:
        return None
    return layer_of.get(parts[1])


@pytest.fixture(scope="module")
def graph() -> tuple[list[Import], set[str]]:
    files = source_files()
    modules = {module_name(p) for p in files}
    return [i for p in files for i in imports_of(p, modules)], modules


def test_the_table_names_every_package_and_root_module(graph):
    layer_of, may = layer_table()
    assert {"root", "estimator", "terrain", "locating", "outputs", "cli"} <= set(may)
    _, modules = graph
    unplaced = sorted(m for m in modules if m != "appliance" and layer(m, layer_of) is None)
    assert unplaced == []
    unknown = sorted(a for allowed in may.values() for a in allowed if a not in may)
    assert unknown == []


#: the modules that import ``appliance`` for its ``__version__`` alone: the CLI, and the logs' metadata
VERSION_READERS = {"appliance.cli.main", "appliance.acquisition.log_metadata"}


def test_no_import_climbs_a_layer(graph):
    layer_of, may = layer_table()
    imports, _ = graph
    upward = []
    for i in imports:
        if i.source == "appliance" or (i.target == "appliance" and i.source in VERSION_READERS):
            continue  # the package's lazy public names, and the modules reading the version
        src, dst = layer(i.source, layer_of), layer(i.target, layer_of)
        if dst is None or src is None or dst not in may[src]:
            upward.append(f"{i.source}:{i.line} -> {i.target}")
    assert upward == []


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan), or a module importing itself."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1 or v in edges.get(v, ()):
                found.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return found


def test_cycles_are_found_by_the_check():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle(graph):
    imports, modules = graph
    edges: dict[str, set[str]] = {}
    for i in imports:
        target = i.target
        while target not in modules and "." in target:
            target = target.rpartition(".")[0]
        # a package's __init__ importing its own modules is how it re-exports them, not a cycle
        if i.source != target and not (target.startswith(i.source + ".") and i.source != "appliance"):
            edges.setdefault(i.source, set()).add(target)
    edges.pop("appliance", None)
    assert cycles(edges) == []


def test_every_deferred_import_says_why(graph):
    imports, _ = graph
    silent = sorted(f"{i.source}:{i.line} -> {i.target}" for i in imports if i.deferred and not i.commented)
    assert silent == []
