"""The structure drawn from the imports: ``pipeline.core`` imports nothing outside itself; the
renderers, detectors and estimators stand on it alone; the stages stack above in data-flow order
(estimate → metrics → report / recording → run → batch → cli); no circles. Every import counts,
those inside functions and under ``TYPE_CHECKING`` included."""

from __future__ import annotations

import ast
from pathlib import Path

from tests.conftest import REPO

PACKAGES = ("pipeline", "detectors", "renderers")

#: (layer, folder or module), lowest first: ``pipeline/``'s folders are its layers, with the two stages
#: that stand alone (estimate, calibrate) at the top of ``pipeline/``; a module may import its own group
#: and lower layers only
LAYERS: list[tuple[int, tuple[str, ...]]] = [
    (0, ("pipeline.core",)),
    (1, ("renderers",)), (1, ("detectors",)), (1, ("pipeline.estimators",)),
    (2, ("pipeline.evaluation",)),
    (3, ("pipeline.estimate",)), (3, ("pipeline.calibrate",)),
    (4, ("pipeline.present",)),
    (5, ("pipeline.app",)),
]


def module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports() -> dict[str, set[str]]:
    """Module → the project modules it imports (anywhere in its source)."""
    mods = {module_name(p): p for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in mods.items():
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                continue
            found |= {t for t in targets if t in mods and t != name}
        graph[name] = found
    return graph


def group(module: str) -> tuple[int, str]:
    """(layer, group) of a module: the longest matching prefix."""
    best = max(((len(p), layer, p) for layer, prefixes in LAYERS for p in prefixes
                if module == p or module.startswith(p + ".")), default=None)
    assert best is not None, f"{module} is in no layer: add it to LAYERS"
    return best[1], best[2] if best[1] else "pipeline.core"


def test_imports_follow_the_data_flow():
    wrong = []
    for mod, targets in imports().items():
        if mod in PACKAGES:
            continue
        layer, grp = group(mod)
        for t in targets:
            if t in PACKAGES:
                continue
            t_layer, t_grp = group(t)
            if t_grp != grp and t_layer >= layer:
                wrong.append(f"{mod} → {t}")
    assert not wrong, "imports against the data flow:\n" + "\n".join(sorted(wrong))


def test_no_import_circles():
    graph = imports()
    state: dict[str, int] = {}
    cycles = []

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for t in sorted(graph.get(m, ())):
            if state.get(t) == 1:
                cycles.append(" → ".join([*path[path.index(t):], t]))
            elif t not in state:
                visit(t, [*path, t])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert not cycles, "import circles:\n" + "\n".join(cycles)


def test_functions_are_short():
    """No function or method in the packages is over 60 lines (docstring and signature included)."""
    long = []
    for pkg in PACKAGES:
        for path in sorted((REPO / pkg).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno >= 60:
                    long.append(f"{path.relative_to(REPO)}:{node.lineno} {node.name} ({node.end_lineno - node.lineno + 1})")
    assert not long, "\n".join(long)


def test_pipeline_folders_are_its_layers():
    """``pipeline/`` holds its layers as folders (each named in :data:`LAYERS`) and, flat, only the
    stages that stand alone: a new module must go into a layer's folder or be named here."""
    named = {p for _, prefixes in LAYERS for p in prefixes}
    flat = {f"pipeline.{p.stem}" for p in (REPO / "pipeline").glob("*.py") if p.stem != "__init__"}
    folders = {f"pipeline.{p.name}" for p in (REPO / "pipeline").iterdir() if (p / "__init__.py").is_file()}
    assert flat <= named, f"flat modules in no layer: {sorted(flat - named)}"
    assert folders <= named, f"folders in no layer: {sorted(folders - named)}"
    assert len(folders) >= 4


def test_modules_are_short():
    """No module in the packages is over 500 lines."""
    long = [f"{p.relative_to(REPO)} ({n})" for pkg in PACKAGES for p in sorted((REPO / pkg).rglob("*.py"))
            if (n := len(p.read_text().splitlines())) > 500]
    assert not long, "\n".join(long)


def _parameters(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    a = node.args
    names = [*a.posonlyargs, *a.args, *a.kwonlyargs, *([a.vararg] if a.vararg else []), *([a.kwarg] if a.kwarg else [])]
    return len([n for n in names if n.arg not in ("self", "cls")])


def test_few_functions_take_ten_parameters():
    """Settings travel as objects (:class:`pipeline.core.settings.RunSettings`, state records), not
    as long parameter lists: at most two library functions take ten or more parameters. The
    command-line commands (``@app.command``) are left out: typer takes each option as a parameter."""
    many = []
    for pkg in PACKAGES:
        for path in sorted((REPO / pkg).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and _parameters(node) >= 10 \
                        and not any("app.command" in ast.unparse(d) for d in node.decorator_list):
                    many.append(f"{path.relative_to(REPO)}:{node.lineno} {node.name} ({_parameters(node)})")
    assert len(many) <= 2, "\n".join(many)
