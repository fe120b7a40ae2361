"""The package's imports follow the data flow and have no cycles (issue 19, item 1).

The oracle is the source itself, read with :mod:`ast` (top-level and function-level imports
count; ``if TYPE_CHECKING:`` blocks do not, since they never run). Two properties:

* no import cycle between any two modules of ``harvest_qp``;
* each layer imports only the layers below it in the data flow (:data:`LAYERS`): the QP core
  never imports the configuration files' schema, the runtime, perception, the reference laws, the
  harvest application or the lab; the runtime (robot interface, runner) never imports perception
  or what is above it; perception never imports the reference laws; the reference laws never
  import the application; the lab, the real robots, viewer, sweep and CLI are shells above
  everything.

Bug it catches (planted once): ``from harvest_qp.references import ReachingCentering`` inside a
function of ``harvest_qp/perception/stem.py`` fails ``test_layers_import_only_downwards``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import harvest_qp

PACKAGE = Path(harvest_qp.__file__).resolve().parent

#: Layers from the bottom of the data flow up; a module's layer is the longest matching prefix.
#: A layer may import its own layer and any layer listed before it.
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("core", ("harvest_qp.exceptions", "harvest_qp.validation", "harvest_qp.robot", "harvest_qp.configuration",
              "harvest_qp.collision", "harvest_qp.tasks", "harvest_qp.limits", "harvest_qp.backends",
              "harvest_qp.qp_kernels", "harvest_qp.solver", "harvest_qp.task_controller", "harvest_qp.pinv")),
    ("config", ("harvest_qp.config",)),
    ("runtime", ("harvest_qp.runtime",)),
    ("perception", ("harvest_qp.perception",)),
    ("references", ("harvest_qp.references",)),
    ("harvest", ("harvest_qp.harvest",)),
    ("shells", ("harvest_qp.sim", "harvest_qp.real", "harvest_qp.viewer", "harvest_qp.sweep", "harvest_qp.cli",
                "harvest_qp.__main__")),
]
RANK = {name: i for i, (name, _) in enumerate(LAYERS)}
#: Upward imports allowed on purpose, each with its reason.
ALLOWED_UPWARD = {
    ("harvest_qp.config.episode_schema", "harvest_qp.sim.scene"):
        "scene.params keys are checked by the lab's own VineSceneParams (a lazy import inside the "
        "validator), so check-config names a bad scene key before any episode runs",
}


def _modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = ("harvest_qp", *path.relative_to(PACKAGE).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


MODULES = _modules()


def _type_checking_lines(tree: ast.AST) -> set[int]:
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.body:
                skip.update(n.lineno for n in ast.walk(child) if hasattr(n, "lineno"))
    return skip


def _targets(module: str, node: ast.Import | ast.ImportFrom) -> set[str]:
    if isinstance(node, ast.Import):
        names = [alias.name for alias in node.names]
    else:
        base = node.module or ""
        if node.level:
            parts = module.split(".")
            if MODULES[module].name != "__init__.py":
                parts = parts[:-1]
            parts = parts[: len(parts) - (node.level - 1)]
            base = ".".join([*parts, *([base] if base else [])])
        names = [base, *(f"{base}.{alias.name}" for alias in node.names)]
    found = set()
    for name in names:
        while name and name not in MODULES:
            name = name.rpartition(".")[0]
        if name:
            found.add(name)
    return found


def import_graph() -> dict[str, set[str]]:
    """Module -> the harvest_qp modules it imports (a package's __init__ re-exporting its children excluded)."""
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for module, path in MODULES.items():
        tree = ast.parse(path.read_text())
        skip = _type_checking_lines(tree)
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)) and node.lineno not in skip:
                for target in _targets(module, node):
                    own_child = target.startswith(module + ".") and MODULES[module].name == "__init__.py"
                    own_parent = module.startswith(target + ".") and MODULES[target].name == "__init__.py"
                    if target != module and not own_child and not own_parent:
                        graph[module].add(target)
    return graph


def layer_of(module: str) -> str:
    best, length = None, -1
    for name, prefixes in LAYERS:
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > length:
                best, length = name, len(prefix)
    return best if best is not None else ("core" if module == "harvest_qp" else "unassigned")


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (iterative Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = 0
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
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
                    work.append((child, iter(sorted(graph[child]))))
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
                    found.append(sorted(component))
    return found


def test_no_import_cycles():
    assert cycles(import_graph()) == []


def test_every_module_has_a_layer():
    assert [m for m in MODULES if layer_of(m) == "unassigned"] == []


def test_layers_import_only_downwards():
    graph = import_graph()
    upward = sorted(
        f"{module} ({layer_of(module)}) imports {target} ({layer_of(target)})"
        for module, targets in graph.items() for target in targets
        if module != "harvest_qp" and RANK[layer_of(target)] > RANK[layer_of(module)]
        and (module, target) not in ALLOWED_UPWARD
    )
    assert upward == []


def test_cycle_finder_finds_a_planted_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(graph) == [["a", "b", "c"]]
