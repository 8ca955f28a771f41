"""The package's import structure, read from the source: no import circle between modules, and no
import that runs up the layer order of docs/architecture.md ("Import layers") beyond the few
allowed and justified there.

Every ``.py`` file under ``dvsland/`` is parsed with :mod:`ast`; every import counts, at module
level and inside functions and methods alike (a late import is still an import): ``import x``,
``from x import y`` (an edge to ``x.y`` when that is a module, else to ``x``), relative imports
resolved against the importing module, and ``importlib.import_module("literal")`` /
``__import__("literal")``. Imports under ``if TYPE_CHECKING:`` are left out: they never run.
Names built at run time (``import_module(f"dvsland.cli.{name}")``) cannot be read and are left out.

``python tests/test_architecture_imports.py`` prints the circles and the upward imports.
"""

from __future__ import annotations

import ast
from collections import defaultdict, deque
from pathlib import Path
from typing import Dict, Iterator, List, NamedTuple, Optional, Sequence, Set, Tuple

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "dvsland"
DOC = REPO / "docs" / "architecture.md"

#: The layers, lowest first. A module may import its own layer and the layers below it; within a
#: layer (one package), modules may import each other as long as no circle forms. A module belongs
#: to the longest name here that prefixes it; the root ``dvsland`` (``dvsland/__init__.py``,
#: the ``dvsland.simulate`` facade) is only itself. docs/architecture.md lists the same order.
LAYERS: Tuple[str, ...] = (
    "dvsland._version",
    "dvsland.checks",       # argument checks
    "dvsland.pytree",       # the stage contract: state trees, counter-based random numbers, object stages
    "dvsland.native_build", # the build cache of the optional compiled kernels
    "dvsland.compiled",     # torch.compile of the loop's pure functions, with an eager fallback
    "dvsland.allocator",    # the process's memory allocator, set for runs
    "dvsland.plugins",      # the registry mechanism of every extension point
    "dvsland.config",       # typed config, YAML, validation: imports no stage
    "dvsland.layout",       # the batch layout of B descents and its dispersion draws
    "dvsland.terrain",
    "dvsland.render",
    "dvsland.events",
    "dvsland.estimators",
    "dvsland.dynamics",     # Eq. 1 and the closed-form descent
    "dvsland.control",      # the laws and filters; their loop-gain maths uses dynamics
    "dvsland.stages",       # the builder: stages from a config
    "dvsland.report",       # results.json, tables, TensorBoard, figures: what sim writes
    "dvsland.watchdog",     # ends a command stuck in native code after Ctrl-C / SIGTERM
    "dvsland.runs",         # run folders, the interrupt guard
    "dvsland.sim",          # the closed loop and simulate()
    "dvsland",              # the package root: dvsland.simulate
    "dvsland.evaluate",     # open-loop evaluation of the estimators
    "dvsland.campaign",     # Monte Carlo grids, shards, merged reports
    "dvsland.data",         # datasets of flown descents (campaign plans)
    "dvsland.learn",        # the training recipe of the learned estimators (datasets)
    "dvsland.envs",         # the environments around loop_step
    "dvsland.bench",        # benchmarks of every layer below
    "dvsland.cli",          # the dvsland command
)
ROOT = "dvsland"

#: Upward imports allowed, (importer, imported) -> why; at most 3, and each one is named in
#: docs/architecture.md as "`importer` → `imported`" with its justification. None today.
ALLOWED_UPWARD: Dict[Tuple[str, str], str] = {}
MAX_ALLOWED = 3


class Edge(NamedTuple):
    """``importer`` imports ``imported`` at ``file:line``."""

    importer: str
    imported: str
    file: str
    line: int

    def where(self) -> str:
        return f"{self.file}:{self.line}"


# ------------------------------------------------------------------ reading the imports
def module_name(path: Path, root: Path) -> str:
    """``dvsland/events/io.py`` -> ``dvsland.events.io``; a package's ``__init__.py`` is the package."""
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _literal_import(node: ast.Call) -> Optional[str]:
    """The module of ``importlib.import_module("x")`` or ``__import__("x")`` with a literal name."""
    f = node.func
    name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
    arg = node.args[0] if node.args else None
    if name in ("import_module", "__import__") and isinstance(arg, ast.Constant) and isinstance(arg.value, str):
        return arg.value
    return None


def _walk(node: ast.AST) -> Iterator[ast.AST]:
    """Every node below ``node``, leaving out the bodies of ``if TYPE_CHECKING:`` (not their else)."""
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.If) and _is_type_checking(child.test):
            for other in child.orelse:
                yield other
                yield from _walk(other)
            continue
        yield child
        yield from _walk(child)


def _from_base(node: ast.ImportFrom, module: str, is_package: bool) -> str:
    """The absolute module a ``from ... import`` names (relative levels resolved)."""
    if not node.level:
        return node.module or ""
    package = module.split(".") if is_package else module.split(".")[:-1]
    package = package[: len(package) - (node.level - 1)]
    return ".".join(package + ([node.module] if node.module else []))


def raw_imports(tree: ast.AST, module: str, is_package: bool) -> Iterator[Tuple[int, str, Optional[str]]]:
    """(line, module, imported name or None) of every import in ``tree``."""
    for node in _walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name, None
        elif isinstance(node, ast.ImportFrom):
            base = _from_base(node, module, is_package)
            for alias in node.names:
                yield node.lineno, base, alias.name
        elif isinstance(node, ast.Call):
            literal = _literal_import(node)
            if literal:
                yield node.lineno, literal, None


def _target(base: str, name: Optional[str], modules: Set[str]) -> Optional[str]:
    """The package module an import reaches: ``base.name`` if that is a module, else the longest
    module prefix of ``base``; None outside the package."""
    if name and f"{base}.{name}" in modules:
        return f"{base}.{name}"
    while base and base not in modules:
        base = base.rpartition(".")[0]
    return base or None


def import_graph(root: Path = PACKAGE) -> Tuple[Set[str], List[Edge]]:
    """(modules, edges) of the package at ``root``: one edge per import statement and target."""
    files = {module_name(p, root): p for p in sorted(root.rglob("*.py"))}
    modules, edges = set(files), {}
    for mod, path in files.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        for line, base, name in raw_imports(tree, mod, path.name == "__init__.py"):
            target = _target(base, name, modules)
            if target and target != mod:
                edge = Edge(mod, target, str(path.relative_to(root.parent)), line)
                edges.setdefault(edge, edge)
    return modules, list(edges)


# ------------------------------------------------------------------ circles
def _components(modules: Set[str], adj: Dict[str, Set[str]]) -> List[List[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: Dict[str, int] = {}
    low: Dict[str, int] = {}
    stack: List[str] = []
    on_stack: Set[str] = set()
    out: List[List[str]] = []
    for start in sorted(modules):
        if start in index:
            continue
        work = [(start, iter(sorted(adj[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            v, children = work[-1]
            w = next(children, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(adj[w]))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def _shortest_cycle(start: str, members: Set[str], adj: Dict[str, Set[str]]) -> List[str]:
    """The shortest circle [start, ..., start] inside one component (breadth first)."""
    prev: Dict[str, Optional[str]] = {start: None}
    queue = deque([start])
    while queue:
        v = queue.popleft()
        for w in sorted(adj[v] & members):
            if w == start:
                path = [v]
                while prev[path[-1]] is not None:
                    path.append(prev[path[-1]])
                return path[::-1] + [start]
            if w not in prev:
                prev[w] = v
                queue.append(w)
    return [start]


def find_cycles(modules: Set[str], edges: Sequence[Edge]) -> List[List[str]]:
    """One circle per group of modules that import each other round: [a, b, ..., a]."""
    adj: Dict[str, Set[str]] = defaultdict(set)
    for e in edges:
        adj[e.importer].add(e.imported)
    return [_shortest_cycle(comp[0], set(comp), adj) for comp in _components(modules, adj)]


def describe_cycle(cycle: Sequence[str], edges: Sequence[Edge]) -> str:
    """``a -> b (file:line) -> a (file:line)``."""
    first = {}
    for e in edges:
        first.setdefault((e.importer, e.imported), e)
    hops = [f"{b} ({first[(a, b)].where()})" for a, b in zip(cycle, cycle[1:])]
    return " -> ".join([cycle[0]] + hops)


# ------------------------------------------------------------------ layers
def layer_of(module: str) -> Optional[int]:
    """Index in :data:`LAYERS` of ``module`` (longest prefix; the root only for itself)."""
    name = module
    while name:
        if name in LAYERS and (name != ROOT or module == ROOT):
            return LAYERS.index(name)
        name = name.rpartition(".")[0]
    return None


def upward_imports(edges: Sequence[Edge]) -> List[Edge]:
    """The imports whose target sits in a higher layer than the importer (modules in no layer are
    reported by :func:`test_every_module_has_a_layer`)."""
    layers = [(layer_of(e.importer), layer_of(e.imported)) for e in edges]
    return [e for e, (a, b) in zip(edges, layers) if a is not None and b is not None and b > a]


def _doc_section(title: str) -> str:
    text = DOC.read_text(encoding="utf-8")
    start = text.index(f"## {title}")
    end = text.find("\n## ", start + 1)
    return text[start:end if end > 0 else len(text)]


# ------------------------------------------------------------------ the tests
@pytest.fixture(scope="module")
def graph():
    return import_graph()


def test_the_reader_sees_every_kind_of_import(tmp_path):
    """Function-level, relative and import_module imports count; TYPE_CHECKING ones do not."""
    files = {
        "__init__.py": "",
        "low.py": "def f():\n    from .sub import high\n",
        "sub/__init__.py": "from . import high\n",
        "sub/high.py": ("import importlib\nfrom typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                        "    import pkg.sub.deep\nelse:\n    import json\n"
                        "def g():\n    importlib.import_module('pkg.low')\n"),
        "sub/deep.py": "from .. import low\nfrom ..sub.high import g\nimport pkg.sub.high as h\n",
    }
    for name, text in files.items():
        (tmp_path / "pkg" / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "pkg" / name).write_text(text)
    modules, edges = import_graph(tmp_path / "pkg")
    assert {(e.importer, e.imported) for e in edges} == {
        ("pkg.low", "pkg.sub.high"), ("pkg.sub", "pkg.sub.high"), ("pkg.sub.high", "pkg.low"),
        ("pkg.sub.deep", "pkg.low"), ("pkg.sub.deep", "pkg.sub.high")}
    assert find_cycles(modules, edges) == [["pkg.low", "pkg.sub.high", "pkg.low"]]


def test_every_module_has_a_layer(graph):
    modules, _ = graph
    missing = sorted(m for m in modules if layer_of(m) is None)
    assert missing == [], f"modules in no layer (add their package to LAYERS and docs/architecture.md): {missing}"


def test_no_import_circle(graph):
    modules, edges = graph
    cycles = [describe_cycle(c, edges) for c in find_cycles(modules, edges)]
    assert cycles == [], "import circles (move the shared part into the lower module):\n" + "\n".join(cycles)


def test_no_upward_import(graph):
    _, edges = graph
    up = [e for e in upward_imports(edges)
          if (e.importer, e.imported) not in ALLOWED_UPWARD]
    listed = "\n".join(f"{e.where()}: {e.importer} -> {e.imported}" for e in up)
    assert up == [], ("imports up the layer order of docs/architecture.md (move the code to the layer it "
                      "belongs to, or pass it in):\n" + listed)


def test_allowed_upward_imports_are_few_real_and_documented(graph):
    _, edges = graph
    assert len(ALLOWED_UPWARD) <= MAX_ALLOWED
    section = _doc_section("Import layers")
    real = {(e.importer, e.imported) for e in upward_imports(edges)}
    for (a, b), why in ALLOWED_UPWARD.items():
        assert why.strip(), f"{a} -> {b}: say why it is allowed"
        assert (a, b) in real, f"{a} -> {b} is allowed but no longer upward or gone: drop it from ALLOWED_UPWARD"
        assert f"`{a}` → `{b}`" in section, f"docs/architecture.md does not name and justify `{a}` → `{b}`"


def test_docs_list_the_same_layer_order():
    """docs/architecture.md ("Import layers") names the layers in the order of :data:`LAYERS`."""
    section = _doc_section("Import layers")
    start = section.index("```text")
    block = section[start:section.index("```", start + 3)].splitlines()[1:]
    named = [line.split()[0] for line in block if line.split() and line.split()[0].startswith("dvsland")]
    assert tuple(named) == LAYERS


if __name__ == "__main__":  # counts and lists for a quick look
    _modules, _edges = import_graph()
    _cycles = find_cycles(_modules, _edges)
    _up = upward_imports(_edges)
    print(f"{len(_modules)} modules, {len(_edges)} imports, {len(_cycles)} circles, {len(_up)} upward imports")
    for _c in _cycles:
        print("  circle:", describe_cycle(_c, _edges))
    for _e in _up:
        print(f"  upward: {_e.where()}: {_e.importer} -> {_e.imported}")
