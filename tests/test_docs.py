"""Rules of the documentation and of the experiments folder."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXPERIMENTS = ROOT / "experiments"
# what a script could import from tests/: its modules and the folder as a package
TEST_MODULES = {p.stem for p in (ROOT / "tests").glob("*.py")} | {"tests"}


def test_experiments_readme_is_an_index():
    """experiments/README.md is an index of current results (the history is CHANGELOG.md):
    under 600 lines."""
    n = len((EXPERIMENTS / "README.md").read_text().splitlines())
    assert n < 600, f"experiments/README.md has {n} lines"


def offences(source: str) -> list[str]:
    """Where ``source`` changes ``sys.path`` or imports a module of tests/ (line: code)."""
    found = {}
    for node in ast.walk(ast.parse(source)):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            names = [node.module or ""]
        elif isinstance(node, (ast.Call, ast.Assign, ast.AugAssign)):
            code = ast.unparse(node.func if isinstance(node, ast.Call) else node)
            if "sys.path" in code:
                found[node.lineno] = ast.unparse(node)
        if any(n.split(".")[0] in TEST_MODULES for n in names):
            found[node.lineno] = ast.unparse(node)
    return [f"{k}: {v}" for k, v in sorted(found.items())]


def test_experiments_import_only_the_package():
    """No script in experiments/ puts a folder on sys.path or imports from tests/: what an
    experiment needs lives in the fgslam package (or beside it in experiments/)."""
    bad = {
        p.name: found
        for p in sorted(EXPERIMENTS.glob("*.py"))
        if (found := offences(p.read_text()))
    }
    assert not bad, bad


def test_the_import_rule_catches_tests_on_the_path():
    """The check above fails on what experiments did before (tests/ on sys.path, a test
    module imported) and passes the package's imports."""
    before = (
        "import sys\n"
        "from pathlib import Path\n"
        "sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'tests'))\n"
        "from test_map_management import _park\n"
        "import readers_helpers\n"
        "from fgslam.sim.scenes import park_run\n"
    )
    assert [line.split(":")[0] for line in offences(before)] == ["3", "4", "5"]
    assert offences("import numpy as np\nfrom fgslam.sim.scenes import ROOM\n") == []
