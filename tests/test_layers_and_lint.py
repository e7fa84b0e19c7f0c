"""The package's layering contract and its lint, checked with every test run (CI included)."""
import ast
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: a layer and the packages above it, which it must not import (docs/ARCHITECTURE.md)
ABOVE = {
    "dqm/core": ["dqm.distributed", "dqm.runtime", "dqm.vision", "dqm.evaluation", "dqm.experiments",
                 "dqm.commands", "dqm.cli"],
    "dqm/distributed": ["dqm.runtime", "dqm.vision", "dqm.evaluation", "dqm.experiments", "dqm.commands",
                        "dqm.cli"],
}


def imported_modules(path: Path) -> set:
    """Absolute names of every module a file imports (relative imports resolved, at any depth:
    imports inside functions count too)."""
    parts = path.relative_to(ROOT).with_suffix("").parts
    package = list(parts[:-1])  # a module's package; for __init__ the package itself
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                base = node.module
            else:
                base = ".".join(package[:len(package) - (node.level - 1)] + ([node.module] if node.module else []))
            names.add(base)
            names |= {f"{base}.{alias.name}" for alias in node.names}  # "from . import x" may name a module
    return names


def test_resolution_of_relative_imports(tmp_path):
    assert "dqm.validation" in imported_modules(ROOT / "dqm" / "core" / "clustering.py")
    assert "dqm.core.clustering" in imported_modules(ROOT / "dqm" / "core" / "online.py")  # from .clustering
    assert "dqm.core.pairs" in imported_modules(ROOT / "dqm" / "core" / "online.py")  # from . import pairs


@pytest.mark.parametrize("layer", sorted(ABOVE))
def test_lower_layers_import_nothing_above_them(layer):
    offenders = []
    for path in sorted((ROOT / layer).rglob("*.py")):
        bad = sorted(name for name in imported_modules(path)
                     if any(name == top or name.startswith(top + ".") for top in ABOVE[layer]))
        if bad:
            offenders.append(f"{path.relative_to(ROOT)}: {', '.join(bad)}")
    assert not offenders, "imports from a higher layer:\n" + "\n".join(offenders)


def test_ruff_passes():
    """The repository's ruff configuration (pyproject.toml) over the package, tests and scripts."""
    ruff = shutil.which("ruff") or str(Path(sys.executable).with_name("ruff"))
    if not Path(ruff).exists():
        pytest.fail("ruff is not installed: pip install -e '.[test]' installs it")
    p = subprocess.run([ruff, "check", "dqm", "tests", "scripts"], cwd=ROOT, capture_output=True, text=True)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-1000:]
