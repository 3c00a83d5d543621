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
    "training": {"geometry", "model"} | UTIL,
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
TRAINING_MODULES = {"__init__", "step", "state", "checkpoint", "logger"}


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
