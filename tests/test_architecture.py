"""The import graph of the source tree, read with `ast` (nothing is imported): no cycles, and the layering of
docs/architecture.md.

Every `import` / `from ... import` statement counts, wherever it stands: at module level, inside a function (a late
import only hides a dependency from the interpreter's load order, the two modules still need each other), and under
`if TYPE_CHECKING:` (a type-only import still ties one module's meaning to the other's and makes mypy load it).
`from pkg import name` counts as an import of the module `pkg.name` when that module exists, else of `pkg`. Importing
`a.b.c` also runs `a/__init__.py`; that implicit edge is left out (every package whose front re-exports a submodule
would otherwise be a cycle), and instead the ground's own `dynrecon/__init__.py` is checked to import nothing.
`importlib.import_module` calls are not statements and are not seen: the lazy package fronts (`tracking/__init__.py`,
`labeling/__init__.py`) therefore name what they load under `TYPE_CHECKING`, where it counts.
"""

from __future__ import annotations

import ast
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from functools import cache
from itertools import pairwise
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("dynrecon", "sfm", "tracking", "labeling", "reconstruct", "simulation", "batch")
# The shared ground: user errors, atomic writes, folder locks, bounded readers, video opening and names, JSON
# numbers, argument types, the lens model's inverse, progress bars in log files. Every package may import it; it
# imports no package.
GROUND = (
    "dynrecon.errors",
    "dynrecon.names",
    "dynrecon.atomic",
    "dynrecon.lock",
    "dynrecon.readers",
    "dynrecon.video_io",
    "dynrecon.lazy",
    "dynrecon.beside",
    "dynrecon.jsonvalues",
    "dynrecon.arguments",
    "dynrecon.lens",
    "dynrecon.warnings_seen",
    "dynrecon.bar_lines",
)
GROUND_NODE = "ground"
# Nodes of the package graph: a module belongs to the longest of these that prefixes it.
PACKAGE_NODES = (*PACKAGES, "reconstruct.solver", "reconstruct.clocks", "reconstruct.outputs")
# The command line and the pipeline on top of every stage; no stage reaches up to them.
TOP = ("dynrecon.cli", "dynrecon.pipeline", "dynrecon.pipeline_cli", "dynrecon.demo", "dynrecon.__main__")


@dataclass(frozen=True)
class Edge:
    source: str
    target: str
    line: int

    def where(self) -> str:
        return f"{module_path(self.source)}:{self.line}"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def module_path(name: str) -> str:
    path = REPO.joinpath(*name.split("."))
    return str((path / "__init__.py" if path.is_dir() else path.with_suffix(".py")).relative_to(REPO))


@cache
def modules() -> dict[str, Path]:
    found = {}
    for package in PACKAGES:
        for path in sorted((REPO / package).rglob("*.py")):
            found[module_name(path)] = path
    return found


def _is_package(name: str) -> bool:
    return (REPO.joinpath(*name.split(".")) / "__init__.py").is_file()


def _resolve(source: str, node: ast.ImportFrom) -> str:
    """The absolute module of `from <module> import ...` in `source` (relative imports resolved)."""
    if not node.level:
        return node.module or ""
    base = source.split(".") if _is_package(source) else source.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join([*base, node.module] if node.module else base)


def _targets(source: str, tree: ast.AST) -> Iterable[tuple[str, int]]:
    """(imported module name, line) of every import statement anywhere in the module, first-party or not."""
    known = modules()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            module = _resolve(source, node)
            for alias in node.names:
                submodule = f"{module}.{alias.name}"
                yield (submodule if submodule in known else module), node.lineno


@cache
def all_imports() -> tuple[Edge, ...]:
    """Every import, first-party or not (third-party targets keep their dotted name)."""
    edges = []
    for name, path in modules().items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        edges += [Edge(name, target, line) for target, line in _targets(name, tree)]
    return tuple(edges)


@cache
def graph() -> dict[str, list[Edge]]:
    """First-party module -> its imports of other first-party modules."""
    known = modules()
    result: dict[str, list[Edge]] = {name: [] for name in known}
    for edge in all_imports():
        if edge.target in known and edge.target != edge.source:
            result[edge.source].append(edge)
    return result


def node_of(module: str) -> str:
    if module in GROUND:
        return GROUND_NODE
    return max((p for p in PACKAGE_NODES if module == p or module.startswith(p + ".")), key=len)


def _strongly_connected(nodes: Iterable[str], successors: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's components with more than one node (iterative: no recursion limit)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []
    for root in nodes:
        if root in index:
            continue
        work = [(root, iter(sorted(successors.get(root, ()))))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(successors.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    components.append(sorted(component))
    return components


def _path(start: str, goal: str, successors: dict[str, set[str]], allowed: set[str] | None = None) -> list[str]:
    """A shortest path start -> ... -> goal (breadth first), [] when none."""
    previous: dict[str, str] = {}
    frontier = [start]
    while frontier:
        following = []
        for node in frontier:
            for child in sorted(successors.get(node, ())):
                if (allowed is not None and child not in allowed) or child in previous:
                    continue
                previous[child] = node
                if child == goal:
                    chain = [goal]
                    while chain[-1] != start or len(chain) == 1:
                        chain.append(previous[chain[-1]])
                    return chain[::-1]
                following.append(child)
        frontier = following
    return []


def _describe(chain: list[str], edges: dict[tuple[str, str], Edge]) -> str:
    """`a -> b (a.py:12) -> c (b.py:3)`: each step with the import that makes it."""
    steps = [chain[0]]
    steps += [f"{b} ({edges[(a, b)].where()})" for a, b in pairwise(chain)]
    return " -> ".join(steps)


def _module_successors() -> tuple[dict[str, set[str]], dict[tuple[str, str], Edge]]:
    successors: dict[str, set[str]] = {}
    first: dict[tuple[str, str], Edge] = {}
    for source, edges in graph().items():
        for edge in edges:
            successors.setdefault(source, set()).add(edge.target)
            first.setdefault((source, edge.target), edge)
    return successors, first


def _package_successors() -> tuple[dict[str, set[str]], dict[tuple[str, str], Edge]]:
    successors: dict[str, set[str]] = {}
    first: dict[tuple[str, str], Edge] = {}
    for source, edges in graph().items():
        for edge in edges:
            a, b = node_of(source), node_of(edge.target)
            if a != b:
                successors.setdefault(a, set()).add(b)
                first.setdefault((a, b), edge)
    return successors, first


def _cycles(successors: dict[str, set[str]], first: dict[tuple[str, str], Edge]) -> list[str]:
    found = []
    for component in _strongly_connected(sorted(successors), successors):
        members = set(component)
        start = component[0]
        found.append(_describe(_path(start, start, successors, members), first))
    return found


def _reachable(start: str, successors: dict[str, set[str]], stop: Callable[[str], bool]) -> set[str]:
    """Modules reachable from `start`, not going on through those where `stop` holds."""
    seen, todo = {start}, [start]
    while todo:
        node = todo.pop()
        if stop(node):
            continue
        for child in successors.get(node, ()):
            if child not in seen:
                seen.add(child)
                todo.append(child)
    return seen


def _is_under(module: str, prefixes: Iterable[str]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in prefixes)


def _violations(sources: Iterable[str], forbidden: Callable[[str], bool]) -> list[str]:
    """Chains (transitive, every import counted) from a module of `sources` to a first-party module or third-party
    name that is `forbidden`, each up to the first forbidden step."""
    successors, first = _module_successors()
    outside: dict[str, list[Edge]] = {}  # third-party imports, by importing module
    for edge in all_imports():
        if edge.target not in modules():
            outside.setdefault(edge.source, []).append(edge)
    found = []
    for source in sorted(sources):
        reachable = _reachable(source, successors, forbidden)
        allowed = {m for m in reachable if not forbidden(m)}
        for module in sorted(reachable):
            chain = [source] if module == source else _path(source, module, successors, allowed | {module})
            if forbidden(module):
                found.append(_describe(chain, first))
                continue
            for edge in outside.get(module, ()):
                if forbidden(edge.target):
                    found.append(f"{_describe(chain, first)} -> {edge.target} ({edge.where()})")
    return sorted(set(found))


# ----------------------------------------------------------------------------------------------------------


def test_the_scan_sees_the_tree() -> None:
    names = modules()
    assert {"dynrecon.cli", "reconstruct.solver.alternation", "tracking.stage", "labeling.server"} <= set(names)
    edges = {(e.source, e.target) for e in all_imports()}
    assert ("dynrecon.cli", "dynrecon.errors") in edges
    # a late import inside a function counts (tracking's CLI imports its stage in the handler)
    assert ("tracking.cli", "tracking.stage") in edges


def test_no_cycle_between_modules() -> None:
    cycles = _cycles(*_module_successors())
    assert not cycles, "import cycles between modules:\n  " + "\n  ".join(cycles)


def test_no_cycle_between_packages() -> None:
    cycles = _cycles(*_package_successors())
    assert not cycles, "import cycles between packages:\n  " + "\n  ".join(cycles)


def test_the_ground_imports_no_package() -> None:
    successors, first = _module_successors()
    bad = [_describe([g, t], first) for g in GROUND for t in sorted(successors.get(g, ())) if t not in GROUND]
    # importing dynrecon.errors runs dynrecon/__init__.py first: it must stay as light as the ground
    bad += [_describe(["dynrecon", t], first) for t in sorted(successors.get("dynrecon", ()))]
    assert not bad, (
        "the ground (dynrecon.errors, .atomic, .readers, .video_io) imports other modules:\n  " + "\n  ".join(bad)
    )


def test_the_solver_stands_alone() -> None:
    def forbidden(module: str) -> bool:
        if _is_under(module, ("reconstruct",)):  # the package front and the other subpackages too
            return not _is_under(module, ("reconstruct.solver",))
        cli = module.endswith((".cli", "_cli"))
        return cli or _is_under(module, ("sfm", "tracking", "labeling", "simulation", "rerun", *TOP))

    solver = [m for m in modules() if _is_under(m, ("reconstruct.solver",))]
    bad = _violations(solver, forbidden)
    assert not bad, "reconstruct.solver reaches outside the solver:\n  " + "\n  ".join(bad)


def test_reconstruct_does_not_reach_up() -> None:
    reconstruct = [m for m in modules() if _is_under(m, ("reconstruct",))]
    bad = _violations(reconstruct, lambda module: _is_under(module, ("simulation", *TOP)))
    assert not bad, "reconstruct imports the simulation or the dynrecon CLI/pipeline/demo:\n  " + "\n  ".join(bad)
