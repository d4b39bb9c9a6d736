"""The package's shape: one installed name, `silcr`, its data files, and common/ below every component.

The install test builds a wheel of this checkout and installs it (not editable) into a
fresh virtual environment that borrows this one's dependencies, then runs silcr from a
directory holding a `common/` package of its own: before the namespace, silcr installed
`common`, `bench` and `deploy` at the top level and `silcr sweep` started its cells
with `python -m common.cli`, which picked up the wrong `common` there.
"""

from __future__ import annotations

import ast
import os
import shutil
import site
import subprocess
import sys
import venv
from pathlib import Path

import pytest

from tests.helpers import REPO, free_port

COMPONENTS = ("silcr.actor", "silcr.learner", "silcr.buffer_service", "silcr.deploy", "silcr.bench", "silcr.cli",
              "silcr.plot", "silcr.figures", "silcr.stats", "silcr.policy_commands")


def _imports(path: Path) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


@pytest.mark.parametrize("module", sorted(p.name for p in (REPO / "common").glob("*.py")))
def test_common_imports_no_component(module):
    bad = {n for n in _imports(REPO / "common" / module) if n.startswith(COMPONENTS)}
    assert not bad, f"common/{module} imports {bad}: common/ must stay below every component"


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """A fresh venv with silcr installed from a wheel of this checkout (its dependencies borrowed from this venv)."""
    tmp = tmp_path_factory.mktemp("install")
    # Built from a copy: setuptools leaves build/ beside the sources, and a stale one would hide a missing file.
    src = tmp / "src"
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(".git", ".venv", "build", "runs", "results", "*.egg-info",
                                                            "__pycache__", ".pytest_cache", ".hypothesis"))
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-v", "-w",
                            str(tmp / "wheel"), str(src)], check=True, timeout=300, capture_output=True, text=True)
    wheel = next((tmp / "wheel").glob("silcr-*.whl"))
    env_dir = tmp / "venv"
    venv.create(env_dir, with_pip=True)
    bin_dir = env_dir / "bin"
    py = bin_dir / "python"
    target = Path(subprocess.run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                 capture_output=True, text=True, check=True).stdout.strip())
    before = set(os.listdir(target))
    # torch, zenoh, mujoco and the rest come from this venv's site-packages, after the fresh one's own.
    (target / "zz_borrowed_deps.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    subprocess.run([py, "-m", "pip", "install", "-q", "--no-deps", "--no-index", str(wheel)], check=True, timeout=300,
                   capture_output=True)
    added = set(os.listdir(target)) - before - {"zz_borrowed_deps.pth"}
    # Run from a directory with a `common` package that must not be picked up.
    work = tmp / "work"
    (work / "common").mkdir(parents=True)
    (work / "common" / "__init__.py").write_text("raise ImportError('this is the other project\\'s common')\n")
    (work / "common" / "cli.py").write_text("raise SystemExit('the other project\\'s common.cli ran')\n")
    # ... and a `silcr/` folder holding the CLI alone, as a source checkout does: `silcr sweep`
    # started its cells with `python -m silcr.cli`, which found this folder instead of the package.
    (work / "silcr").mkdir()
    (work / "silcr" / "__init__.py").write_text("")
    (work / "silcr" / "cli.py").write_text("raise SystemExit('the checkout\\'s silcr/cli.py ran')\n")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["PATH"] = f"{bin_dir}{os.pathsep}{env.get('PATH', '')}"
    return {"added": added, "target": target, "bin": bin_dir, "work": work, "env": env,
            "build_output": build.stdout + build.stderr}


def test_building_prints_no_warning_about_the_projects_configuration(installed):
    """pyproject.toml as current setuptools expects it: an SPDX license string, data folders declared."""
    warnings = [line.strip() for line in installed["build_output"].splitlines()
                if "Warning" in line and "byte-compiling" not in line]
    assert warnings == [], "\n".join(warnings)


def test_installing_adds_exactly_one_top_level_name_and_the_data_files(installed):
    names = {n for n in installed["added"] if not n.endswith(".dist-info") and n != "__pycache__"}
    assert names == {"silcr"}, installed["added"]
    deploy = installed["target"] / "silcr" / "deploy"
    for data in ("zenoh/router-tls-acl.json5", "zenoh/client-tls.json5", "config/silcr.toml", "make-certs.sh",
                 "docker-compose.yml", "Dockerfile"):
        assert (deploy / data).is_file(), data


def test_the_installed_silcr_runs_beside_another_projects_common(installed, tmp_path):
    run = lambda *args: subprocess.run([str(installed["bin"] / "silcr"), *args], capture_output=True, text=True,  # noqa: E731
                                       cwd=installed["work"], env=installed["env"], timeout=300)
    r = run("sweep", str(REPO / "experiments" / "hopper-30k.toml"), "--dry-run", "--runs-dir", str(tmp_path / "sweep"))
    assert r.returncode == 0 and "9 cells" in r.stdout, r.stdout + r.stderr
    # A one-cell sweep: its cell is a child `silcr train` started from the working directory.
    exp = tmp_path / "tiny.toml"
    exp.write_text('tasks = ["InvertedPendulum-v5"]\nseeds = "0"\n[common]\nhidden = [16, 16]\nlearning_starts = 200\n'
                   'total_steps = 1200\neval_interval = 600\neval_episodes = 1\n[variants.installed]\nalgo = "silcr"\n')
    r = run("sweep", str(exp), "--runs-dir", str(tmp_path / "tiny"), "--port-base", str(free_port()))
    cell = tmp_path / "tiny" / "installed_InvertedPendulum-v5_s0"
    assert r.returncode == 0, r.stdout + r.stderr + (cell / "sweep.log").read_text()
    assert (cell / "progress.csv").read_text().count("\n") >= 3


# -- the house: classes of one concept, modules that do not reach back (issue 40) ------------------------

#: The source folders and the package each installs as (pyproject.toml's package-dir).
PACKAGES = {"silcr": "silcr", "actor": "silcr.actor", "learner": "silcr.learner", "buffer_service": "silcr.buffer_service",
            "common": "silcr.common", "deploy": "silcr.deploy", "bench": "silcr.bench"}
MAX_CLASS_LINES = 180


def _modules() -> dict[str, Path]:
    out = {}
    for folder, package in PACKAGES.items():
        for f in sorted((REPO / folder).glob("*.py")):
            out[package if f.stem == "__init__" else f"{package}.{f.stem}"] = f
    return out


def import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """Which project modules each module imports, at the top or inside a function (TYPE_CHECKING too)."""
    graph = {}
    for name, path in modules.items():
        base = name if path.stem == "__init__" else name.rsplit(".", 1)[0]
        found: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                found |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                pkg = base
                for _ in range(node.level - 1):
                    pkg = pkg.rsplit(".", 1)[0]
                module = (f"{pkg}.{node.module}" if node.module else pkg) if node.level else node.module
                found |= {module} | {f"{module}.{a.name}" for a in node.names}  # `from pkg import module`
        graph[name] = {m for m in found if m in modules and m != name}
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected groups of more than one module (Tarjan): each holds an import circle."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                cycles.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return cycles


def test_no_two_modules_import_each_other_even_through_others():
    cycles = import_cycles(import_graph(_modules()))
    assert not cycles, f"import circles: {cycles}"


def folder_graph(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """Which source folders import which (issue 62): `silcr/` is the top (CLI, API), the others below it."""
    def folder(module: str) -> str:
        parts = module.split(".")
        return parts[1] if len(parts) > 1 and parts[1] in PACKAGES and parts[1] != "silcr" else "silcr"

    out: dict[str, set[str]] = {f: set() for f in PACKAGES}
    for name, imported in graph.items():
        out[folder(name)] |= {folder(m) for m in imported} - {folder(name)}
    return out


def test_folders_import_in_one_direction():
    """No folder-level circle (an import inside a function counts): what lower folders need lives below `silcr/`."""
    cycles = import_cycles(folder_graph(import_graph(_modules())))
    assert not cycles, f"folders that import each other: {cycles}"


def test_the_folder_check_finds_a_lower_folder_reaching_up():
    graph = import_graph(_modules())
    graph["silcr.learner.evaluate"] = graph["silcr.learner.evaluate"] | {"silcr.plot"}
    assert any({"learner", "silcr"} <= set(c) for c in import_cycles(folder_graph(graph)))


def test_the_circle_check_finds_a_circle_through_a_function_level_import():
    """The check itself: a circle closed by an import inside a function (as the CLI and the sweep had) is found."""
    graph = import_graph(_modules())
    graph["silcr.common.config"] = graph["silcr.common.config"] | {"silcr.deploy.sweep"}  # sweep imports config
    assert any("silcr.deploy.sweep" in c and "silcr.common.config" in c for c in import_cycles(graph))
    tree = ast.parse("def f():\n    from silcr.cli import main\n")
    assert any(isinstance(n, ast.ImportFrom) and n.module == "silcr.cli" for n in ast.walk(tree))


def installers_of_signal_handlers() -> list[str]:
    """The modules that call `signal.signal` (install a handler) anywhere."""
    return sorted(name for name, path in _modules().items()
                  if any(isinstance(n, ast.Call) and ast.unparse(n.func) == "signal.signal"
                         for n in ast.walk(ast.parse(path.read_text()))))


def test_signal_handlers_are_installed_in_at_most_two_modules():
    """How Ctrl-C and SIGTERM stop a run is decided in one place (common/lifecycle.py), not per launcher (issue 62)."""
    installers = installers_of_signal_handlers()
    assert len(installers) <= 2 and "silcr.common.lifecycle" in installers, installers


def test_no_module_outside_the_tests_is_longer_than_500_lines():
    """The wire contract, common/protocol.py, may stay whole (issue 62)."""
    long = [f"{name} ({n} lines)" for name, path in _modules().items()
            if name != "silcr.common.protocol" and (n := len(path.read_text().splitlines())) > 500]
    assert not long, long


def test_no_class_outside_the_tests_is_longer_than_180_lines():
    long = [f"{name}.{node.name} ({node.end_lineno - node.lineno + 1} lines)"
            for name, path in _modules().items() for node in ast.walk(ast.parse(path.read_text()))
            if isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno + 1 > MAX_CLASS_LINES]
    assert not long, f"classes over {MAX_CLASS_LINES} lines: {long}"


def test_the_readmes_python_quick_start_runs_as_written_where_silcr_is_installed(installed, tmp_path):
    """The README's Python block, verbatim, in a fresh venv with silcr installed from a wheel (issue 38)."""
    readme = (REPO / "README.md").read_text()
    section = readme.split("## Python quick start", 1)[1]
    code = section.split("```python\n", 1)[1].split("```", 1)[0]
    assert "from silcr import SILCR" in code and "SILCR.load(" in code and ".predict(" in code
    script = tmp_path / "quick_start.py"
    script.write_text(code + "\nprint('ACTION', action)\n")
    r = subprocess.run([str(installed["bin"] / "python"), str(script)], capture_output=True, text=True, cwd=tmp_path,
                       env=installed["env"], timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "ACTION [" in r.stdout and (tmp_path / "pendulum.silcr").is_file()
    assert not (REPO / "pendulum.silcr").exists()
