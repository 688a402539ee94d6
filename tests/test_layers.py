"""The package's layering: which layer may import which, and no import cycles.

Every `import` statement of dali_cli/ and stages/ counts, function-level ones included (they hide
cycles from Python but not from a reader). A module is named by its dotted path; a package's
layer is its first component below dali_cli (dali_cli.store.artifacts -> "store").
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# The layers from the bottom up: a module may import its own layer and the layers below it, never
# one above (a back import). Top-level modules (geometry, sensors, raycast, ...) are layers of their
# own name; "__init__" is dali_cli/__init__.py (the version). A new package must take its place here.
ORDER = [
    "__init__",
    "runtime",  # where code runs: errors, console, cores, workers, device
    "quantities",  # the kinds of number (and profile names): plain checks, no imports
    "store",  # artifacts on disk: manifests, frame sets, box tables
    "geometry",
    "registration",  # scan poses by ICP (dali register): numpy only
    "columns",
    "sensors",
    "raycast",
    "procedural",
    "executors",  # local / Ray engines of the per-frame stages
    "library",
    "world",
    "ptsn",
    "labels",  # pseudo labels and the default score cut
    "detector",  # the model, its training loop and the training stages' driver
    "importers",  # external formats (KITTI label_2, calib, camera fields)
    "evaluation",
    "export",
    "merge",  # several frame sets into one (a target of several drives)
    "synth",
    "ppcg",
    "reporting",
    "stages",
    "commands",  # the click layer
    "cli",
]
RANK = {name: rank for rank, name in enumerate(ORDER)}
LEAVES = {f"dali_cli.runtime.{m}" for m in ("errors", "console", "cores", "workers")}


def modules() -> dict[str, Path]:
    found = {}
    for package in ("dali_cli", "stages"):
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            found[name] = path
    return found


def imports_of(path: Path, name: str, known: dict[str, Path]) -> set[str]:
    """The project modules `path` imports (resolved to the longest known module name)."""
    is_package = path.name == "__init__.py"
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        targets = []
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".")
                anchor = anchor if is_package else anchor[:-1]
                anchor = anchor[: len(anchor) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            targets = [f"{base}.{alias.name}" for alias in node.names] + [base]
        for target in targets:
            parts = target.split(".")
            while parts and ".".join(parts) not in known:
                parts.pop()
            if parts and ".".join(parts) != name:
                out.add(".".join(parts))
    return out


def graph() -> dict[str, set[str]]:
    known = modules()
    return {name: imports_of(path, name, known) for name, path in known.items()}


def layer(module: str) -> str:
    parts = module.split(".")
    return parts[0] if parts[0] == "stages" else (parts[1] if len(parts) > 1 else "__init__")


def test_no_import_cycles():
    edges = graph()
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(node):  # Tarjan's strongly connected components
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in edges.get(node, ()):
            if nxt not in edges:
                continue
            # a package and its own modules are one unit for cycle purposes
            if nxt.startswith(node + ".") or node.startswith(nxt + "."):
                continue
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                top = stack.pop()
                on_stack.discard(top)
                component.append(top)
                if top == node:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for node in sorted(edges):
        if node not in index:
            visit(node)
    assert not cycles, f"import cycles: {cycles}"


def test_every_layer_has_its_place():
    assert {layer(module) for module in graph()} <= set(ORDER)


def test_no_import_runs_back_up_a_layer():
    back = [
        (module, target)
        for module, targets in graph().items()
        for target in targets
        if RANK[layer(target)] > RANK[layer(module)]
    ]
    assert not back, "imports of a higher layer (module -> import):\n" + "\n".join(
        f"  {m} -> {t}" for m, t in sorted(back)
    )


def test_the_order_catches_a_back_import():
    """A property of the checker: the store importing the detector would be caught."""
    assert RANK[layer("dali_cli.detector.train")] > RANK[layer("dali_cli.store.manifest")]
    assert layer("stages.pretrain") == "stages" and layer("dali_cli.cli") == "cli"


def test_runtime_leaves_import_nothing_of_dali():
    edges = graph()
    for leaf in LEAVES:
        assert not edges[leaf], f"{leaf} imports {edges[leaf]}"


def test_the_graph_sees_function_level_imports():
    """A property of the checker itself: an import inside a function is an edge."""
    edges = graph()
    assert "dali_cli.runtime.machine" in edges["dali_cli.runtime.device"]
    assert any(t.startswith("dali_cli.store") for t in edges["dali_cli.evaluation.evaluate"])
