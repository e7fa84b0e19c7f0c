"""The package's layering contract and its lint, checked with every test run (CI included)."""
import ast
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

TOP = ["dqm.commands", "dqm.cli"]
APPLICATION = ["dqm.vision", "dqm.evaluation", "dqm.plots", "dqm.camnet", "dqm.benchmark"]
#: a layer (a package folder or a module file) and the packages above it, which it must not import
#: (docs/ARCHITECTURE.md); every package and module of dqm is in one (a test checks it)
ABOVE = {
    "dqm/core": ["dqm.distributed", "dqm.runtime"] + APPLICATION + TOP,
    "dqm/distributed": ["dqm.runtime"] + APPLICATION + TOP,
    "dqm/runtime": APPLICATION + TOP,
    "dqm/vision": ["dqm.distributed", "dqm.runtime", "dqm.evaluation", "dqm.plots", "dqm.camnet", "dqm.benchmark"]
    + TOP,
    "dqm/evaluation.py": ["dqm.distributed", "dqm.runtime", "dqm.plots", "dqm.camnet", "dqm.benchmark"] + TOP,
    "dqm/plots.py": ["dqm.distributed", "dqm.runtime", "dqm.camnet", "dqm.benchmark"] + TOP,
    "dqm/camnet": ["dqm.distributed", "dqm.runtime", "dqm.benchmark"] + TOP,
    "dqm/benchmark.py": ["dqm.distributed", "dqm.runtime", "dqm.camnet"] + TOP,
    "dqm/commands": ["dqm.cli"],
}
#: the support modules under every layer: they import none of the layers (the package's face, __init__, and the
#: program, __main__ and cli, import them all)
SUPPORT = ["io", "lazy_exports", "logging_config", "outputs", "process_env", "progress", "signals", "synthetic",
           "validation", "wording"]
for _name in SUPPORT:
    ABOVE[f"dqm/{_name}.py"] = ["dqm.core", "dqm.distributed", "dqm.runtime"] + APPLICATION + TOP


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


def layer_files(layer: str):
    path = ROOT / layer
    return [path] if path.suffix == ".py" else sorted(path.rglob("*.py"))


def module_graph() -> dict:
    """Every dqm module and the dqm modules it imports (at any depth: imports inside functions count)."""
    files = {}
    for path in sorted((ROOT / "dqm").rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    graph = {}
    for name, path in files.items():
        deps = set()
        for imported in imported_modules(path):
            while imported and imported not in files:  # "from x import name": the module x
                imported = imported.rpartition(".")[0]
            if imported and imported != name and imported != "dqm":  # the package's face: lazy names only
                deps.add(imported)
        graph[name] = deps
    return graph


def test_every_package_and_module_is_in_a_layer():
    covered = {path for layer in ABOVE for path in layer_files(layer)}
    missing = [str(p.relative_to(ROOT)) for p in sorted((ROOT / "dqm").rglob("*.py"))
               if p not in covered and p.parent != ROOT / "dqm"]
    missing += [str(p.relative_to(ROOT)) for p in sorted((ROOT / "dqm").glob("*.py"))
                if p not in covered and p.stem not in ("__init__", "__main__", "cli")]
    assert not missing, "not in any layer of the import contract: " + ", ".join(missing)


def test_no_module_imports_itself_through_others():
    """No import cycle among dqm's modules (Tarjan's strongly connected components)."""
    graph = module_graph()
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert not cycles, "import cycles: " + "; ".join(" <-> ".join(c) for c in cycles)


@pytest.mark.parametrize("layer", sorted(ABOVE))
def test_lower_layers_import_nothing_above_them(layer):
    offenders = []
    for path in layer_files(layer):
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


#: runtime modules that print instead of logging, and why
RUNTIME_WITHOUT_LOGGER = {
    "__init__": "the package's face",
    "console": "the job's console view: its lines are the product, on the stream the user gave",
    "router": "its [router] lines are the `dqm router` command's own output (ready, listening, refusals)",
    "limits": "a data class and its options: nothing happens there to log",
}


def test_every_runtime_module_logs_through_the_dqm_logger_tree():
    """Issue 38: 6 of 101 modules logged; each runtime module logs through logging.getLogger("dqm...")."""
    silent = [p.stem for p in sorted((ROOT / "dqm" / "runtime").glob("*.py"))
              if p.stem not in RUNTIME_WITHOUT_LOGGER and 'getLogger("dqm' not in p.read_text()]
    assert not silent, "runtime modules without a logger of the dqm tree: " + ", ".join(silent)


def test_dqm_processes_start_with_their_environment_defaults(tmp_path):
    """The dqm command sets OPENBLAS_THREAD_TIMEOUT and NUMPY_MADVISE_HUGEPAGE for itself before numpy loads (so
    numpy makes no huge-page requests in it), and the launcher for every child; a value the caller's environment
    has is kept (dqm.process_env)."""
    import os
    import subprocess
    import sys

    from dqm.process_env import ENV_DEFAULTS, with_env_defaults
    from dqm.runtime.launcher import Processes

    assert with_env_defaults({}) == ENV_DEFAULTS == {"OPENBLAS_THREAD_TIMEOUT": "4", "NUMPY_MADVISE_HUGEPAGE": "0"}
    assert with_env_defaults({"OPENBLAS_THREAD_TIMEOUT": "9"}) == {**ENV_DEFAULTS, "OPENBLAS_THREAD_TIMEOUT": "9"}
    # numpy is not loaded before main, which sets the variables first (--version then loads numpy for the kernel)
    probe = ("import os, sys, dqm.cli as c\nbefore = 'numpy' in sys.modules\ntry:\n    c.main(['--version'])\n"
             "except SystemExit:\n    pass\nfrom numpy._core import multiarray as m\n"
             "print(before, os.environ.get('OPENBLAS_THREAD_TIMEOUT'), m._get_madvise_hugepage())")
    env = {k: v for k, v in os.environ.items() if k not in ENV_DEFAULTS}
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, timeout=60)
    assert out.stdout.split()[-3:] == ["False", "4", "False"], out.stdout + out.stderr
    out = subprocess.run([sys.executable, "-c", probe], env={**env, "OPENBLAS_THREAD_TIMEOUT": "9",
                                                             "NUMPY_MADVISE_HUGEPAGE": "1"},
                         capture_output=True, text=True, timeout=60)
    assert out.stdout.split()[-2:] == ["9", "True"]
    (tmp_path / "envprobe.py").write_text("import os\nprint(os.environ.get('OPENBLAS_THREAD_TIMEOUT'), "
                                          "os.environ.get('NUMPY_MADVISE_HUGEPAGE'))\n")
    procs = Processes()
    child = procs.start([], tmp_path / "c.log", env={**env, "PYTHONPATH": str(tmp_path)}, module="envprobe")
    child.wait(timeout=60)
    procs.stop_all()
    assert (tmp_path / "c.log").read_text().split()[-2:] == ["4", "0"]
