"""The layering of the package (docs/architecture.md), pinned by scanning every import:
entry points -> app floor -> library; inside the library each package imports only the
packages below it. A module-level or function-level import counts the same."""

from __future__ import annotations

import ast
import os

import pytest

SRC = os.path.join(os.path.dirname(__file__), "..", "src", "seglocnet_jax")

# Unit -> the units it may import. Units are top-level modules or packages of seglocnet_jax.
ENTRY = {"train", "evaluate", "preview"}
UTIL = {"config_util", "fileio"}
ALLOWED = {
    "geometry": set(),
    "config_util": set(),
    "fileio": set(),
    "maps": {"geometry"} | UTIL,
    "sim": {"geometry", "maps"} | UTIL,
    "solver": {"geometry"},
    "losses": {"geometry", "solver"},
    "metrics": {"geometry"},
    "data": {"geometry", "maps", "sim", "solver"} | UTIL,
    "model": {"geometry", "solver", "losses"} | UTIL,
    "viz": {"geometry", "maps"} | UTIL,
    "evaluation": {"geometry", "solver", "metrics", "model", "viz"},
    "training": {"geometry", "model", "data"} | UTIL,  # data: the batch schema
    "tracking": {"geometry", "solver"},
    "sequential": {
        "geometry",
        "solver",
        "metrics",
        "viz",
        "maps",
        "data",
        "evaluation",
        "tracking",
    }
    | UTIL,
    "app": {
        "geometry",
        "maps",
        "sim",
        "solver",
        "losses",
        "metrics",
        "data",
        "model",
        "viz",
        "evaluation",
        "training",
        "tracking",
        "sequential",
    }
    | UTIL,
}
for _entry in ENTRY:
    ALLOWED[_entry] = {"app"}
TRAINING_MODULES = {"__init__", "step", "state", "checkpoint", "checksums", "logger"}
# Inside data: its top level is the dataset format, below the two producers of datasets (the
# simulator's, real ones), which never import each other. Sub-unit -> what it may import.
DATA_FORMAT = {"geometry", "maps", "data"} | UTIL
DATA_ALLOWED = {
    "data": DATA_FORMAT,
    "data.simulated": DATA_FORMAT | {"sim", "data.simulated"},
    "data.real": DATA_FORMAT | {"solver", "data.real"},
}


def _modules():
    for root, _, files in os.walk(SRC):
        for name in files:
            if name.endswith(".py"):
                path = os.path.join(root, name)
                rel = os.path.relpath(path, SRC)[:-3].split(os.sep)
                yield path, rel


def _imports(path: str, rel: list[str]):
    tree = ast.parse(open(path).read(), path)
    package = ["seglocnet_jax", *rel[:-1]]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                yield ".".join(base + ([node.module] if node.module else []))
            elif node.module:
                yield node.module
                for alias in node.names:  # `from seglocnet_jax import maps`
                    if node.module == "seglocnet_jax":
                        yield f"seglocnet_jax.{alias.name}"


def _unit(rel: list[str]) -> str:
    return rel[0]


def _data_unit(parts: list[str]) -> str:
    """``parts`` of a module under seglocnet_jax -> its data sub-unit ("data", "data.real", ...),
    or its unit outside data."""
    if parts[0] != "data":
        return parts[0]
    if len(parts) > 2 or (len(parts) == 2 and os.path.isdir(os.path.join(SRC, *parts))):
        return f"data.{parts[1]}"
    return "data"


def test_every_unit_has_a_layer():
    units = {_unit(rel) for _, rel in _modules()} - {"__init__"}
    assert units <= set(ALLOWED), f"add {units - set(ALLOWED)} to the layering table"


@pytest.mark.parametrize(
    "path, rel", sorted(_modules()), ids=lambda x: "/".join(x) if isinstance(x, list) else ""
)
def test_imports_respect_the_layers(path, rel):
    unit = _unit(rel)
    if unit == "__init__":
        return
    allowed = ALLOWED[unit] | {unit}
    bad = []
    for name in _imports(path, rel):
        parts = name.split(".")
        if parts[0] == "hydra" and unit not in ENTRY | {"app"}:
            bad.append(name)  # library code never imports Hydra
        if parts[0] != "seglocnet_jax" or len(parts) < 2:
            continue
        if parts[1] not in allowed:
            bad.append(name)
    assert not bad, f"{'/'.join(rel)}.py imports {bad}; {unit} may import only {sorted(allowed)}"


def test_training_holds_only_step_state_checkpoint_and_logging():
    names = {
        os.path.splitext(n)[0]
        for n in os.listdir(os.path.join(SRC, "training"))
        if n.endswith(".py")
    }
    assert names <= TRAINING_MODULES


def test_every_data_subpackage_has_a_layer():
    subs = {f"data.{n}" for n in os.listdir(os.path.join(SRC, "data"))}
    subs = {s for s in subs if os.path.isdir(os.path.join(SRC, *s.split(".")))} - {
        "data.__pycache__"
    }
    assert subs <= set(DATA_ALLOWED), f"add {subs - set(DATA_ALLOWED)} to DATA_ALLOWED"


@pytest.mark.parametrize(
    "path, rel",
    sorted(m for m in _modules() if m[1][0] == "data"),
    ids=lambda x: "/".join(x) if isinstance(x, list) else "",
)
def test_data_format_is_below_its_producers(path, rel):
    unit = _data_unit(rel)
    bad = [
        name
        for name in _imports(path, rel)
        if name.startswith("seglocnet_jax.")
        and _data_unit(name.split(".")[1:]) not in DATA_ALLOWED[unit]
    ]
    assert not bad, f"{'/'.join(rel)}.py imports {bad}; {unit} may import only {DATA_ALLOWED[unit]}"


def _module_graph() -> dict[str, set[str]]:
    """Dotted module -> the package's modules it imports (``from pkg import module`` resolved
    to the module; ``from pkg import name`` to the package's ``__init__``)."""
    names = {
        ".".join(["seglocnet_jax", *(rel[:-1] if rel[-1] == "__init__" else rel)])
        for _, rel in _modules()
    }
    graph = {}
    for path, rel in _modules():
        me = ".".join(["seglocnet_jax", *(rel[:-1] if rel[-1] == "__init__" else rel)])
        tree = ast.parse(open(path).read(), path)
        package = ["seglocnet_jax", *rel[:-1]]
        edges = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                edges |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(
                        package[: len(package) - node.level + 1] + ([base] if base else [])
                    )
                for alias in node.names:
                    sub = f"{base}.{alias.name}"
                    edges.add(sub if sub in names else base)
        graph[me] = {e for e in edges if e in names and e != me}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycle():
    cycles = _cycles(_module_graph())
    assert not cycles, f"modules that import each other: {cycles}"


def test_the_cycle_check_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
