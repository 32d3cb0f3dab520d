"""The package's shape: lint clean, no private names across modules, the loop alone in train.py,
no benchmark inside the package, one set-up helper in every notebook."""

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "geodepth_lite"


def test_ruff_check_passes():
    try:
        import ruff  # noqa: F401
    except ImportError:
        pytest.fail("ruff is not installed: run `python -m pip install -r environment.txt`")
    done = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", str(ROOT)], cwd=ROOT,
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr


def _first_party_modules() -> set[str]:
    return {p.stem for p in PACKAGE.glob("*.py")}


def test_no_module_imports_a_private_name_from_another():
    """``from x import _y`` or ``x._y`` across modules of the package (and the benchmarks)."""
    modules = _first_party_modules()
    offences = []
    for path in sorted([*PACKAGE.glob("*.py"), *(ROOT / "benchmarks").glob("*.py")]):
        tree = ast.parse(path.read_text())
        aliases = {}  # local name -> first-party module it stands for
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                mod = (node.module or "").split(".")[-1]
                first_party = node.level > 0 or (node.module or "").startswith("geodepth_lite")
                for a in node.names:
                    if not first_party:
                        continue
                    if a.name in modules:
                        aliases[a.asname or a.name] = a.name
                    elif a.name.startswith("_") and mod != path.stem:
                        offences.append(f"{path.name}: from {node.module} import {a.name}")
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.startswith("geodepth_lite."):
                        aliases[a.asname or a.name.split(".")[-1]] = a.name.split(".")[-1]
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.attr.startswith("_")
                    and not node.attr.startswith("__") and aliases.get(node.value.id, path.stem) != path.stem):
                offences.append(f"{path.name}:{node.lineno}: {node.value.id}.{node.attr}")
    assert not offences, offences


def test_train_py_is_the_loop_alone():
    source = (PACKAGE / "train.py").read_text()
    long = [f"{n.name}: {n.end_lineno - n.lineno + 1} lines" for n in ast.walk(ast.parse(source))
            if isinstance(n, ast.FunctionDef) and n.end_lineno - n.lineno + 1 > 60]
    assert not long, long
    names = {n.name for n in ast.parse(source).body if isinstance(n, (ast.FunctionDef, ast.ClassDef))}
    assert {"fit", "Trainer", "get_lr_factor", "compute_losses", "validate"} <= names
    assert not names & {"make_config", "save_checkpoint", "load_model", "predict_depth", "add_arguments_train"}


def _import_graph() -> dict[str, set[str]]:
    """{module: package modules it imports}, counting imports inside functions too."""
    modules = _first_party_modules()
    graph = {}
    for path in PACKAGE.glob("*.py"):
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.level > 0 or (node.module or "").startswith("geodepth_lite")):
                sub = (node.module or "").split(".")[-1]
                deps |= {sub} if sub in modules else {a.name for a in node.names if a.name in modules}
            elif isinstance(node, ast.Import):
                deps |= {a.name.split(".")[1] for a in node.names if a.name.startswith("geodepth_lite.")}
        graph[path.stem] = deps - {path.stem}
    return graph


def _cycle(graph: dict[str, set[str]]) -> list[str]:
    """One import cycle of ``graph`` as [a, b, ..., a], or [] when there is none (depth-first search)."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str]:
        state[node] = 1
        path.append(node)
        for dep in sorted(graph.get(node, ())):
            if state.get(dep) == 1:
                return path[path.index(dep):] + [dep]
            if dep not in state and (found := visit(dep)):
                return found
        state[node] = 2
        path.pop()
        return []

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return []


def test_the_package_has_no_import_cycle():
    """Every import between package modules counts, the ones inside functions included."""
    assert not _cycle(_import_graph()), " -> ".join(_cycle(_import_graph()))


def test_the_cycle_check_finds_a_cycle():
    """The check can fail: a cycle hidden behind a function-level import is found."""
    assert _cycle({"checkpoint": {"utils"}, "train": {"checkpoint"}, "utils": set()}) == []
    assert _cycle({"checkpoint": {"train"}, "train": {"checkpoint", "utils"}, "utils": set()}) == [
        "checkpoint", "train", "checkpoint"]
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]


def test_no_benchmark_ships_inside_the_package():
    assert not list(PACKAGE.glob("bench*.py"))
    assert {"bench_render.py", "bench_sdf.py"} <= {p.name for p in (ROOT / "benchmarks").glob("*.py")}


@pytest.mark.parametrize("path", sorted((ROOT / "notebooks").glob("[0-9][0-9]_*.ipynb")), ids=lambda p: p.stem)
def test_every_notebook_sets_up_through_the_shared_helper(path):
    cells = [c for c in json.loads(path.read_text())["cells"] if c["cell_type"] == "code"]
    assert "parameters" in cells[0]["metadata"].get("tags", [])
    setup = "".join(cells[1]["source"])
    assert "notebook.setup(profile, run_dir" in setup
    for pasted in ("seed must be", "case must be", "n_examples must be", "utils.runs_dir()", "resolve_run_dir"):
        assert pasted not in setup, pasted
