"""The packages' layering (the import contracts in pyproject.toml) and the lint configuration.

``common`` is the shared kernel and imports no other package of the project;
the runtime (``camera_worker``, ``fusion_server``) imports only what is below
it; the harnesses (synthetic worlds, evaluation, calibration tools, readers)
sit above the runtime and the umbrella command on top. Imports inside
functions count as much as those at the top of a module.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_every_import_contract_is_kept() -> None:
    tool = Path(sys.executable).with_name("lint-imports")
    run = subprocess.run([str(tool), "--no-cache"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    assert "0 broken" in run.stdout


def test_the_kernel_imports_no_other_package_of_the_project() -> None:
    """Read without the tool: no module of common/ names another project package in any import."""
    import ast

    others = {"camera_worker", "fusion_server", "synth", "calibrate", "view", "notify", "evaluation", "voxelwatch"}
    found = []
    for path in sorted((ROOT / "common").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
                [node.module] if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 else [])
            found += [f"{path.relative_to(ROOT)}:{node.lineno} imports {n}" for n in names if n.split(".")[0] in others]
    assert not found, "\n".join(found)


def test_ruff_finds_nothing_on_the_whole_tree() -> None:
    """The lint configuration in pyproject.toml ([tool.ruff]) holds for every file."""
    tool = Path(sys.executable).with_name("ruff")
    run = subprocess.run([str(tool), "check", "--no-cache", "--output-format", "concise", "."], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
