"""The onboard side (runtime, drone, models) never imports torch, onnx or dadiff.export."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FORBIDDEN = ("torch", "onnx", "dadiff.export", "torchvision")


def test_importing_onboard_packages_loads_no_torch():
    code = ("import sys, dadiff.runtime, dadiff.drone, dadiff.models\n"
            f"bad = sorted(m for m in sys.modules\n"
            f"             if m.split('.')[0] in {FORBIDDEN[:2]!r} or m.startswith('dadiff.export'))\n"
            "print(','.join(bad)); sys.exit(1 if bad else 0)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, f"onboard import pulled in: {result.stdout} {result.stderr}"


def test_no_onboard_source_file_imports_the_training_side():
    offenders = []
    for folder in ("runtime", "drone", "models"):
        for path in (REPO / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
                names = []
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom):
                    names = [("." * node.level) + (node.module or "")]
                for name in names:
                    if name.split(".")[0] in ("torch", "onnx", "torchvision") or "export" in name.split("."):
                        offenders.append(f"{path.relative_to(REPO)}: {name}")
    assert not offenders, offenders
