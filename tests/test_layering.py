"""Imports run one way down (docs/ARCHITECTURE.md): no module imports one from a layer above its own, and no
import cycle exists between modules, counting the imports made inside functions too (a lazy import still ties
two modules together).

The graph is read statically from the sources (every ``import`` and ``from ... import`` statement outside an
``if TYPE_CHECKING:`` block), so the test needs none of the optional packages.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("envs", "rotation", "adapters")
SCRIPT_DIRS = ("scripts", "experiments")

LAYERS: tuple[tuple[str, ...], ...] = (
    ("envs",),
    ("rotation.configs", "rotation.interrupt", "rotation.runs", "rotation.hardware", "rotation.policies"),
    ("rotation.policy", "rotation.data", "rotation.sim_warp", "rotation.sim_hardware"),
    ("rotation.tactile.models", "rotation.tactile.ssl"),
    ("rotation.tactile", "rotation.train", "rotation.il"),
    ("adapters",),
    ("rotation.bundles",),
    ("rotation.evaluate", "rotation.deploy"),
    ("rotation.jobs", "rotation.cli"),
    ("scripts", "experiments"),
)
"""The layers from the ground up; a module belongs to the layer of the longest prefix that names it. The table is
the one in docs/ARCHITECTURE.md, which says why each layer sits where it does."""

FORBIDDEN: dict[str, tuple[str, ...]] = {
    "envs": ("torch", "rotation", "adapters"),
    "rotation.hardware": ("torch", "mujoco", "envs"),
}
"""Third-party and project packages a package never imports, whatever the layers allow."""


def layer_of(module: str) -> int:
    if module == "rotation":
        return 0  # the namespace package's own __init__ (a docstring)
    best, layer = -1, -1
    for i, prefixes in enumerate(LAYERS):
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and len(p) > best:
                best, layer = len(p), i
    if layer < 0:
        raise AssertionError(f"{module} is in no layer of LAYERS: add it to the table (and docs/ARCHITECTURE.md)")
    return layer


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[0] in SCRIPT_DIRS:
        return ".".join(parts)  # scripts/x.py -> scripts.x
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def sources() -> dict[str, Path]:
    found = {}
    for top in (*PACKAGES, *SCRIPT_DIRS):
        for p in sorted((ROOT / top).rglob("*.py")) if (ROOT / top).is_dir() else []:
            if "__pycache__" not in p.parts:
                found[module_name(p)] = p
    return found


def imported_names(source: str) -> set[tuple[str, str]]:
    """Every absolute import statement as (module, name): ``import a.b`` gives ("a.b", ""), ``from a.b import c``
    gives ("a.b", "c")."""
    tree = ast.parse(source)
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip.update(id(n) for n in ast.walk(node))
    names: set[tuple[str, str]] = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            names.update((a.name, "") for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.update((node.module, a.name) for a in node.names)
    return names


def graph(modules: dict[str, str]) -> dict[str, set[str]]:
    """Module -> the project modules it imports. ``from a.b import c`` is an edge to the module a.b.c if there is
    one (importing a submodule), else to a.b; a name outside the project is no edge."""
    edges: dict[str, set[str]] = {}
    for mod, text in modules.items():
        out = set()
        for module, name in imported_names(text):
            target = f"{module}.{name}" if f"{module}.{name}" in modules else module
            while target and target not in modules:
                target = target.rpartition(".")[0]
            if target and target != mod:
                out.add(target)
        edges[mod] = out
    return edges


def upward(edges: dict[str, set[str]]) -> list[str]:
    return sorted(f"{a} (layer {layer_of(a)}) imports {b} (layer {layer_of(b)})"
                  for a, deps in edges.items() for b in deps if layer_of(b) > layer_of(a))


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = 0
    for root in sorted(edges):
        if root in index:
            continue
        work = [(root, iter(sorted(edges[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(edges.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                comp = []
                while True:
                    m = stack.pop()
                    on_stack.discard(m)
                    comp.append(m)
                    if m == node:
                        break
                if len(comp) > 1:
                    found.append(sorted(comp))
    return found


def forbidden(modules: dict[str, str]) -> list[str]:
    bad = []
    for mod, text in modules.items():
        for owner, banned in FORBIDDEN.items():
            if mod == owner or mod.startswith(owner + "."):
                for module, _ in imported_names(text):
                    if any(module == b or module.startswith(b + ".") for b in banned):
                        bad.append(f"{mod} imports {module} ({owner} never imports {', '.join(banned)})")
    return sorted(set(bad))


def test_the_checks_catch_what_they_should():
    """On a made-up graph: an import up a layer, a cycle, and a banned package are each reported."""
    modules = {"envs.a": "import torch\nfrom rotation.policy import f", "rotation.policy": "import envs.a",
               "rotation.policy.x": "from rotation.policy import y",
               "rotation.policy.y": "from rotation.policy.x import z", "adapters.m": "from envs.a import f"}
    edges = graph(modules)
    assert any(line.startswith("envs.a (layer 0) imports rotation.policy") for line in upward(edges))
    assert ["rotation.policy.x", "rotation.policy.y"] in cycles(edges)
    assert ["envs.a", "rotation.policy"] in cycles(edges)
    assert any("envs.a imports torch" in line for line in forbidden(modules))
    assert not upward({"adapters.m": {"envs.a"}})


def test_every_module_is_in_a_layer():
    for mod in sources():
        layer_of(mod)


def test_no_module_imports_from_a_layer_above_its_own():
    modules = {m: p.read_text("utf-8") for m, p in sources().items()}
    assert len(modules) > 100, f"found only {len(modules)} modules under {ROOT}"
    bad = upward(graph(modules))
    assert not bad, "imports that run back up (move what both need down, or the importer up):\n" + "\n".join(bad)


def test_no_import_cycles():
    modules = {m: p.read_text("utf-8") for m, p in sources().items()}
    found = cycles(graph(modules))
    assert not found, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in found)


def test_envs_and_hardware_stay_free_of_what_they_must_not_import():
    modules = {m: p.read_text("utf-8") for m, p in sources().items()}
    bad = forbidden(modules)
    assert not bad, "\n".join(bad)
