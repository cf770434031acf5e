"""The layers import one way: the science core (pwm) imports neither the service nor the workers,
and in the service only the command line, which wires the parts together, imports the workers;
no module imports another that imports it back; and a downlink's stages import only the stages
before them, the catalog's shared parts and the science core."""

from __future__ import annotations

import ast
from collections.abc import Collection, Mapping
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def imported_packages(path: Path) -> set[str]:
    """The top-level packages a module imports, wherever in it (inside functions too)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add(node.module.split(".")[0])
    return found


def offenders(package: str, forbidden: set[str], allowed: str | None = None) -> dict[str, set[str]]:
    modules = sorted((ROOT / package).rglob("*.py"))
    assert modules, package
    return {str(m.relative_to(ROOT)): bad for m in modules
            if (allowed is None or not m.relative_to(ROOT).is_relative_to(allowed))
            and (bad := imported_packages(m) & forbidden)}


def module_name(path: Path, root: Path = ROOT) -> str:
    """The dotted name of a module under `root` (a package by its __init__.py)."""
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(path: Path, known: Collection[str], root: Path = ROOT) -> set[str]:
    """The modules of `known` that a module imports, wherever in it (inside functions too):
    `import x.y` imports x.y; `from x import y` imports x, and x.y where that is a module;
    relative imports are resolved against the module's package."""
    name = module_name(path, root)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1]
                                + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            found |= {base} | {f"{base}.{alias.name}" for alias in node.names}
    return {m for m in found if m in known and m != name}


def import_cycles(graph: Mapping[str, Collection[str]]) -> list[list[str]]:
    """The cycles of an import graph: each set of modules that import one another, in turn or
    around a loop, sorted (strongly connected components of more than one module)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles = []

    def visit(module: str) -> None:  # Tarjan's algorithm
        index[module] = low[module] = len(index)
        stack.append(module)
        for other in graph[module]:
            if other not in index:
                visit(other)
                low[module] = min(low[module], low[other])
            elif other in stack:
                low[module] = min(low[module], index[other])
        if low[module] == index[module]:
            component = stack[stack.index(module):]
            del stack[stack.index(module):]
            if len(component) > 1:
                cycles.append(sorted(component))

    for module in sorted(graph):
        if module not in index:
            visit(module)
    return sorted(cycles)


def test_the_science_core_imports_no_service_or_workers():
    assert offenders("pwm", {"service", "workers"}) == {}


def test_only_the_command_line_of_the_service_imports_the_workers():
    assert offenders("service", {"workers"}, allowed="service/cli") == {}


def test_the_walk_finds_imports_inside_functions(tmp_path):
    module = tmp_path / "m.py"
    module.write_text("def f():\n    from workers.tasks import x\n    import service.db\n")
    assert imported_packages(module) == {"workers", "service"}


def test_no_module_imports_another_that_imports_it_back():
    paths = {module_name(p): p for package in ("pwm", "service", "workers")
             for p in sorted((ROOT / package).rglob("*.py"))}
    graph = {name: imported_modules(path, paths) for name, path in paths.items()}
    assert "workers.app" in graph["workers.tasks"] and "service.conductor" in graph["service.run"]
    assert import_cycles(graph) == []


STAGES = ("service.ingest", "service.spg", "service.coverage", "service.refinement", "service.publish",
          "service.lidar", "service.conductor")
"""A downlink's stages in the method's order: catalogue, adjust poses, weigh, plan and refine, fuse
and publish, strip-adjust the lidar; the conductor that calls them in that order last."""
SHARED = {"service.db", "service.rows", "service.settings", "service.kernels", "service.views",
          "service.versions", "service.fusion_blocks", "service.artifacts", "service.jobs", "service.lidar_shots"}
"""What every stage may use: the catalog's engine, rows and settings, its kernels, views, versions
(and the fusion blocks a version keeps), stored files, jobs table and lidar shots as placed now."""


def test_each_stage_imports_only_the_stages_before_it():
    paths = {module_name(p): p for p in sorted((ROOT / "service").rglob("*.py"))}
    for k, stage in enumerate(STAGES):
        service = {m for m in imported_modules(paths[stage], paths) if m.startswith("service.")}
        assert service <= SHARED | set(STAGES[:k]), (stage, service - SHARED - set(STAGES[:k]))


def test_the_import_graph_finds_loops_through_relative_and_from_imports(tmp_path):
    package = tmp_path / "p"
    (package / "sub").mkdir(parents=True)
    for name, text in {"__init__.py": "", "a.py": "from p.sub import b\n", "sub/__init__.py": "",
                       "sub/b.py": "def f():\n    from .. import c\n", "c.py": "import p.a\n",
                       "d.py": "from p import a\n"}.items():
        (package / name).write_text(text)
    paths = {module_name(p, tmp_path): p for p in sorted(package.rglob("*.py"))}
    graph = {name: imported_modules(path, paths, tmp_path) for name, path in paths.items()}
    assert graph["p.a"] == {"p.sub", "p.sub.b"} and graph["p.sub.b"] == {"p", "p.c"}
    assert import_cycles(graph) == [["p.a", "p.c", "p.sub.b"]]


def test_importing_the_api_builds_no_celery_app():
    import subprocess
    import sys

    code = ("import sys, service.api, service.api.app\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('workers', 'celery')))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True, capture_output=True,
                         text=True).stdout
    assert out.strip() == "[]"
