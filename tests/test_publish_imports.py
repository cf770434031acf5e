"""Publication publishes: fusing and publishing a version imports neither the console (whose
documents are made by their own module, after publication or on request) nor matplotlib."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_publication_imports_neither_the_console_nor_matplotlib():
    code = ("import sys, service.publish\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] == 'matplotlib'"
            " or m == 'service.console' or m.startswith('service.console.')))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True, capture_output=True,
                         text=True).stdout
    assert out.strip() == "[]"
