"""The layers import one way: the science core (pwm) imports neither the service nor the workers,
and in the service only the command line, which wires the parts together, imports the workers."""

from __future__ import annotations

import ast
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


def test_the_science_core_imports_no_service_or_workers():
    assert offenders("pwm", {"service", "workers"}) == {}


def test_only_the_command_line_of_the_service_imports_the_workers():
    assert offenders("service", {"workers"}, allowed="service/cli") == {}


def test_the_walk_finds_imports_inside_functions(tmp_path):
    module = tmp_path / "m.py"
    module.write_text("def f():\n    from workers.tasks import x\n    import service.db\n")
    assert imported_packages(module) == {"workers", "service"}


def test_importing_the_api_builds_no_celery_app():
    import subprocess
    import sys

    code = ("import sys, service.api, service.api.app\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('workers', 'celery')))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True, capture_output=True,
                         text=True).stdout
    assert out.strip() == "[]"
