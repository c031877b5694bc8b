"""The package's layers, as the folder tree shows them: each imports only the layers below it,
and no module imports itself back through others (no import cycles, lazy imports included)."""

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent / "mrcert"

# What each layer may import (besides itself and mrcert.errors).
ALLOWED = {
    "core": set(),
    "scenes": {"core"},
    "data": {"core", "scenes"},
    "formats": set(),
    "infra": {"core"},
    "reporting": {"core", "infra"},
    "tasks": {"core", "scenes", "data", "formats", "infra", "reporting"},
    "__main__": {"core", "scenes", "data", "formats", "infra", "reporting", "tasks"},
}


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path) -> set[str]:
    """Every mrcert module ``path`` imports, at any depth of the file (lazy imports included)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("mrcert"):
            found.add(node.module)
            found.update(f"{node.module}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("mrcert"))
    return found


MODULES = {module_name(p): p for p in ROOT.rglob("*.py")}


def graph() -> dict[str, set[str]]:
    return {m: {i for i in imports(p) if i in MODULES and i != m} for m, p in MODULES.items()}


def layer(module: str) -> str:
    return module.split(".")[1] if module.count(".") else "errors"


def test_each_layer_imports_only_the_layers_below_it():
    wrong = sorted(
        (m, i)
        for m, deps in graph().items()
        for i in deps
        if layer(m) in ALLOWED and layer(i) not in ALLOWED[layer(m)] | {layer(m), "errors", "mrcert"}
    )
    assert wrong == []


def test_no_import_cycles():
    edges = graph()
    index, low, stack, on_stack, cycles, counter = {}, {}, [], set(), [], [0]

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = counter[0]
        counter[0] += 1
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
                cycles.append(sorted(component))

    for v in edges:
        if v not in index:
            visit(v)
    assert cycles == []


MODULE_NAME = re.compile(r"\bmrcert\.(\w+)")


def named_in_strings(path: Path) -> set[str]:
    """The mrcert layers a module names in its string constants (``"mrcert.tasks.x:run"``, what
    an import test cannot see), its docstrings aside (bare strings: cross-references for the reader)."""
    tree = ast.parse(path.read_text())
    prose = {
        id(node.value) for node in ast.walk(tree) if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)
    }
    return {
        name
        for node in ast.walk(tree)
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in prose
        for name in MODULE_NAME.findall(node.value)
        if name in ALLOWED
    }


def test_no_layer_names_a_layer_above_it_in_a_string():
    wrong = sorted(
        (m, name)
        for m, path in MODULES.items()
        if layer(m) in ALLOWED
        for name in named_in_strings(path)
        if name not in ALLOWED[layer(m)] | {layer(m)}
    )
    assert wrong == []


def test_every_task_is_a_class_that_runs_and_summarises_its_log():
    """Each ``conf/task/<name>.yaml`` names its :class:`Task` subclass (``_target_``); the class
    runs the task, and summarises its per-image log when it writes one."""
    from mrcert.infra.tasks import TASKS, Task

    names = sorted(p.stem for p in (ROOT.parent / "conf" / "task").glob("*.yaml"))
    assert sorted(TASKS) == names and len(names) == 12
    for name, task in TASKS.items():
        assert isinstance(task, Task) and type(task).run is not Task.run, name
        assert (type(task).summarize is not Task.summarize) == (task.log is not None), name
