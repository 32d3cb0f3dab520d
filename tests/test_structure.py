"""The package's shape, its subpackage datasets/ included: lint clean, no private names across
modules, the loop alone in train.py, no function over 60 lines, imports at the top of a module
(but the heavy or optional ones, each with its reason), no import cycle, no benchmark inside the
package, no notebook named in reproduce.py, one set-up helper in every notebook."""

import ast
import io
import json
import re
import subprocess
import sys
import tokenize
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


def _package_files() -> list[Path]:
    """Every module file of the package, those of its subpackages (``datasets/``) included."""
    return sorted(p for p in PACKAGE.rglob("*.py") if not any(part.startswith(".") for part in p.parts))


def _module_name(path: Path) -> str:
    """A package file's module name, relative to the package: ``train``, ``datasets`` for
    ``datasets/__init__.py``, ``datasets.synthetic``; the package's own ``__init__.py`` is ``__init__``."""
    parts = list(path.relative_to(PACKAGE).with_suffix("").parts)
    if parts[-1] == "__init__" and len(parts) > 1:
        parts.pop()
    return ".".join(parts)


def _first_party_modules() -> set[str]:
    return {_module_name(p) for p in _package_files()}


def _label(path: Path) -> str:
    return str(path.relative_to(ROOT))


def _first_party_imports(node: ast.AST, package: list[str], modules: set[str]) -> list[tuple[str, str | None, str]]:
    """The package imports of one ``import`` / ``from ... import`` statement in a file of (sub)package
    ``package`` (folder names under the package: [] at the top, ["datasets"] in datasets/), as
    (module read, name taken from it or None when the name is that module itself, local name bound)."""
    if isinstance(node, ast.Import):
        return [(a.name.removeprefix("geodepth_lite."), None, a.asname or a.name.split(".")[-1])
                for a in node.names if a.name.startswith("geodepth_lite.")]
    if not isinstance(node, ast.ImportFrom):
        return []
    if node.level:
        if node.level - 1 > len(package):
            return []
        parts = package[:len(package) - (node.level - 1)] + (node.module.split(".") if node.module else [])
    elif node.module == "geodepth_lite" or (node.module or "").startswith("geodepth_lite."):
        parts = node.module.split(".")[1:]
    else:
        return []
    source = ".".join(parts) or "__init__"
    found = []
    for a in node.names:
        sub = ".".join([*parts, a.name])
        found.append((sub, None, a.asname or a.name) if sub in modules else (source, a.name, a.asname or a.name))
    return found


def test_no_module_imports_a_private_name_from_another():
    """``from x import _y`` or ``x._y`` across modules of the package, its subpackages (and the benchmarks)."""
    modules = _first_party_modules()
    offences = []
    files = [(p, _module_name(p), list(p.relative_to(PACKAGE).parent.parts)) for p in _package_files()]
    files += [(p, f"benchmarks.{p.stem}", []) for p in sorted((ROOT / "benchmarks").glob("*.py"))]
    for path, own, package in files:
        tree = ast.parse(path.read_text())
        aliases = {}  # local name -> first-party module it stands for
        for node in ast.walk(tree):
            for source, name, local in _first_party_imports(node, package, modules):
                if name is None:
                    aliases[local] = source
                elif name.startswith("_") and source != own:
                    offences.append(f"{_label(path)}: from {source} import {name}")
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.attr.startswith("_")
                    and not node.attr.startswith("__") and aliases.get(node.value.id, own) != own):
                offences.append(f"{_label(path)}:{node.lineno}: {node.value.id}.{node.attr}")
    assert not offences, offences


MAX_FUNCTION_LINES = 60


def test_no_function_is_over_60_lines():
    """Every function and method of the package, from its ``def`` line to its last line."""
    long = [f"{_label(path)}:{n.lineno}: {n.name} is {n.end_lineno - n.lineno + 1} lines"
            for path in _package_files() for n in ast.walk(ast.parse(path.read_text()))
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))
            and n.end_lineno - n.lineno + 1 > MAX_FUNCTION_LINES]
    assert not long, long


def test_train_py_is_the_loop_alone():
    source = (PACKAGE / "training" / "train.py").read_text()
    names = {n.name for n in ast.parse(source).body if isinstance(n, (ast.FunctionDef, ast.ClassDef))}
    assert {"fit", "Trainer", "get_lr_factor", "compute_losses", "validate"} <= names
    assert not names & {"make_config", "save_checkpoint", "load_model", "predict_depth", "add_arguments_train"}


# The only imports that may sit inside a function: heavy ones (VTK, matplotlib, papermill) that
# would slow every `import geodepth_lite...` and `--help`, or optional / platform-specific ones
# (imageio, tifffile and pytest: a GPU machine may have torch, numpy, scipy, Pillow, tqdm and PyYAML only).
# pyplot at module level could also pick a GUI backend on import. nbgrader's gradebook (SQLAlchemy) is read
# by `course grades` alone.
LATE_IMPORTS = {"pyvista", "vtk", "vtkmodules", "matplotlib", "papermill", "nbformat", "IPython", "ipywidgets",
                "imageio_ffmpeg", "fcntl", "scipy", "nbgrader",
                # needed only by public datasets' readers: training and gpu-check run on GPU images without them
                "imageio", "tifffile",
                "pytest",  # gpu-check runs the CUDA tests only where pytest is installed
                "sqlalchemy",  # nbgrader's gradebook: `course grades` only
                "plotly"}  # plotly.js for a standalone 3D page only: building a 3D view needs no plotly
_PRAGMA = re.compile(r"\b(noqa(:[\s\w,]*)?|type:\s*ignore\S*|pragma:[^#]*)", re.IGNORECASE)  # not reasons


def _reason(comment: str | None) -> bool:
    """True when ``comment`` (a ``# ...`` token) says something besides pragmas like ``noqa``."""
    return comment is not None and re.search(r"[A-Za-z]{3,}", _PRAGMA.sub("", comment.lstrip("#"))) is not None


def misplaced_imports(source: str) -> list[str]:
    """``line: why`` for each import inside a function of ``source`` that should be at the top of the
    module: one not in ``LATE_IMPORTS`` (a relative import never is), or one of those without a
    reason comment on its own line(s) or on a comment line right above it."""
    comments = {tok.start[0]: tok.string for tok in tokenize.generate_tokens(io.StringIO(source).readline)
                if tok.type == tokenize.COMMENT}
    lines = source.splitlines()
    found, seen = [], set()
    for func in ast.walk(ast.parse(source)):
        if not isinstance(func, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for node in ast.walk(func):
            if not isinstance(node, (ast.Import, ast.ImportFrom)) or node.lineno in seen:
                continue
            seen.add(node.lineno)
            if isinstance(node, ast.Import):
                roots = {a.name.split(".")[0] for a in node.names}
            else:
                roots = {"." * node.level + (node.module or "").split(".")[0]}
            text = lines[node.lineno - 1].strip()
            if not roots <= LATE_IMPORTS:
                found.append(f"{node.lineno}: {text}: move it to the top of the module")
                continue
            above = lines[node.lineno - 2].strip() if node.lineno > 1 else ""
            own = [comments.get(i) for i in range(node.lineno, node.end_lineno + 1)]
            if not any(map(_reason, own)) and not (above.startswith("#") and _reason(above)):
                found.append(f"{node.lineno}: {text}: say in a comment why it is imported here")
    return found


def test_imports_sit_at_the_top_but_heavy_or_optional_ones():
    """Inside a function only what ``LATE_IMPORTS`` lists, and each with its reason."""
    offences = [f"{_label(path)}:{o}" for path in _package_files()
                for o in misplaced_imports(path.read_text())]
    assert not offences, offences


def test_the_import_check_can_fail():
    numpy_late = "import os\n\ndef f():\n    import numpy as np  # fast enough\n    return np.zeros(1)\n"
    assert [o.split(":")[0] for o in misplaced_imports(numpy_late)] == ["4"]
    relative_late = "def f():\n    from . import utils  # reasons do not help\n    return utils\n"
    assert len(misplaced_imports(relative_late)) == 1
    pyvista_bare = "def f():\n    import pyvista as pv\n    return pv\n"
    assert len(misplaced_imports(pyvista_bare)) == 1
    pyvista_noqa = "def f():\n    import pyvista as pv  # noqa: F401\n    return pv\n"
    assert len(misplaced_imports(pyvista_noqa)) == 1
    pyvista_far = "# VTK: heavy\n\ndef f():\n    x = 1\n    import pyvista as pv\n    return pv, x\n"
    assert len(misplaced_imports(pyvista_far)) == 1
    pyvista_said = "def f():\n    import pyvista as pv  # VTK: heavy, needed only to build meshes\n    return pv\n"
    pyvista_above = "def f():\n    # VTK: heavy, needed only to build meshes\n    import pyvista as pv\n    return pv\n"
    fcntl_try = ("def f():\n    try:\n        import fcntl  # POSIX only\n    except ImportError:\n"
                 "        return None\n    return fcntl\n")
    top = "import numpy as np\n\n\ndef f():\n    return np.zeros(1)\n"
    for fine in (pyvista_said, pyvista_above, fcntl_try, top):
        assert misplaced_imports(fine) == [], fine


def _import_graph() -> dict[str, set[str]]:
    """{module: package modules it imports}, counting imports inside functions too; submodules are
    named ``datasets.synthetic``. Reading a submodule from outside its subpackage runs the
    subpackage's ``__init__.py`` first, so that counts as importing the subpackage too."""
    modules = _first_party_modules()
    graph = {}
    for path in _package_files():
        own, package = _module_name(path), list(path.relative_to(PACKAGE).parent.parts)
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            for source, _, _ in _first_party_imports(node, package, modules):
                parts = source.split(".")
                deps |= {".".join(parts[:i]) for i in range(1, len(parts) + 1) if package[:i] != parts[:i]}
                deps.add(source)
        graph[own] = {d for d in deps if d in modules} - {own}
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


def test_the_import_graph_sees_the_subpackage():
    """The scans above read datasets/ too, its relative imports resolved both ways."""
    graph = _import_graph()
    assert {"data.datasets", "data.datasets.base", "data.datasets.synthetic", "data.datasets.subsets"} <= set(graph)
    assert {"core.camera", "data.datasets.base"} <= graph["data.datasets.endoslam"]  # from ...core import camera
    assert "data.datasets.synthetic" in graph["data.datasets"] and "data.datasets" in graph["evaluation.evaluate"]
    outside = {"data.x": set(), "data.datasets.y": set(), "data.datasets": set()}
    from_top = _first_party_imports(ast.parse("from geodepth_lite.data.datasets.y import Z").body[0], [],
                                    set(outside))
    assert from_top == [("data.datasets.y", "Z", "Z")]
    inside = _first_party_imports(ast.parse("from .. import x").body[0], ["data", "datasets"], set(outside))
    assert inside == [("data.x", None, "x")]


def _outside_the_method(graph: dict[str, set[str]]) -> dict[str, list[str]]:
    """{module of core/: the modules outside core/ it imports}, for those that import any."""
    inside = {m for m in graph if m == "core" or m.startswith("core.")}
    found = {m: sorted(graph[m] - inside) for m in sorted(inside)}
    return {m: deps for m, deps in found.items() if deps}


def test_the_methods_wing_imports_nothing_outside_itself():
    """core/ (the paper's method: camera, network, losses, SDF, search, metrics) is the ground floor."""
    graph = _import_graph()
    assert {"core.camera", "core.model", "core.losses", "core.sdf", "core.nnsearch", "core.metrics"} <= set(graph)
    assert _outside_the_method(graph) == {}


def test_the_wing_check_finds_an_import_from_outside():
    graph = _import_graph()
    graph["core.losses"] = graph["core.losses"] | {"config"}
    assert _outside_the_method(graph) == {"core.losses": ["config"]}


# The wings from the ground floor up (docs/architecture.md): a wing imports only from the wings before it in
# this order and from the top-level ``utils``. training and views share a floor and do not import each other.
WING_FLOORS = {"core": 1, "data": 2, "training": 3, "views": 3, "evaluation": 4, "apps": 5, "workbook": 5}


def _wing_climbs(graph: dict[str, set[str]]) -> list[str]:
    """Each import from a wing into a wing on its own or a higher floor, as "module -> imported module"."""
    def wing(module: str) -> str | None:
        top = module.split(".")[0]
        return top if top in WING_FLOORS else None
    found = []
    for module, deps in sorted(graph.items()):
        for dep in sorted(deps):
            a, b = wing(module), wing(dep)
            if a and b and a != b and WING_FLOORS[b] >= WING_FLOORS[a]:
                found.append(f"{module} -> {dep}")
    return found


def test_every_module_sits_in_a_wing_but_the_entry_points_and_utils():
    tops = {m.split(".")[0] for m in _import_graph()}
    assert tops - set(WING_FLOORS) == {"__init__", "__main__", "cli", "utils"}


def test_each_wing_imports_only_from_the_wings_below_it():
    assert _wing_climbs(_import_graph()) == []


def test_the_wing_order_check_finds_an_import_from_above():
    graph = _import_graph()
    graph["evaluation.gallery"] = graph["evaluation.gallery"] | {"apps.predict"}  # the former reader in the CLI
    graph["training.train"] = graph["training.train"] | {"views.viz"}
    assert _wing_climbs(graph) == ["evaluation.gallery -> apps.predict", "training.train -> views.viz"]


def test_the_cycle_check_finds_a_cycle():
    """The check can fail: a cycle hidden behind a function-level import is found."""
    assert _cycle({"checkpoint": {"utils"}, "train": {"checkpoint"}, "utils": set()}) == []
    assert _cycle({"checkpoint": {"train"}, "train": {"checkpoint", "utils"}, "utils": set()}) == [
        "checkpoint", "train", "checkpoint"]
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]


# Where a run's configuration is made: the commands, ``reproduce`` and the notebook set-up make the profile
# (``config.profile``) or a configuration (``config.make_config``) once and pass the object down.
CONFIG_EDGES = {"training.config", "training.train_cli", "training.train_many", "workbook.reproduce",
                "workbook.notebook", "apps.gpu_check", "apps.bundle"}
CONFIG_MAKERS = {"make_config", "get_profile", "profile"}


def config_makers_called(source: str) -> list[str]:
    """The calls in ``source`` that make a run's configuration from a profile's name, as "line: name":
    ``config.make_config(...)``, ``config.get_profile(...)``, ``config.profile(...)``, or those names imported
    from ``config`` and called bare."""
    tree = ast.parse(source)
    imported = {a.asname or a.name for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
                and (node.module or "").split(".")[-1] == "config" for a in node.names if a.name in CONFIG_MAKERS}
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        f = node.func
        if isinstance(f, ast.Attribute) and f.attr in CONFIG_MAKERS and isinstance(f.value, ast.Name) \
                and f.value.id == "config":
            found.append(f"{node.lineno}: config.{f.attr}")
        elif isinstance(f, ast.Name) and f.id in imported:
            found.append(f"{node.lineno}: {f.id}")
    return found


def test_no_module_below_the_edge_makes_a_run_config():
    """Below the edge a run's configuration arrives as an object (``config.Profile``, ``config.RunConfig``);
    the profile's name does not travel down to be looked up again."""
    below = {_module_name(path): config_makers_called(path.read_text()) for path in _package_files()
             if _module_name(path) not in CONFIG_EDGES}
    assert {m: calls for m, calls in below.items() if calls} == {}
    edges = {_module_name(path) for path in _package_files() if config_makers_called(path.read_text())}
    assert edges <= CONFIG_EDGES and "workbook.reproduce" in edges and "workbook.notebook" in edges


def test_the_config_edge_check_finds_a_lookup_below_the_edge():
    planted = ("from geodepth_lite.training import config\n"
               "from geodepth_lite.training.config import make_config as mk\n"
               "def sets(profile):\n    prof = config.get_profile(profile)\n    return mk(profile, 1, 0), prof\n"
               "def fine(prof):\n    return prof.run(1, 0), config.config_hash({})\n")
    assert config_makers_called(planted) == ["4: config.get_profile", "5: mk"]


def test_no_benchmark_ships_inside_the_package():
    assert not list(PACKAGE.rglob("bench*.py"))
    assert {"bench_render.py", "bench_sdf.py"} <= {p.name for p in (ROOT / "benchmarks").glob("*.py")}


def test_reproduce_knows_no_notebook_by_name():
    """reproduce.py finds the notebooks (``NN_*.ipynb``) and runs what it finds: no notebook's name,
    nor its ``NN_`` number, appears in its source."""
    source = (PACKAGE / "workbook" / "reproduce.py").read_text()
    names = set()
    for path in (ROOT / "notebooks").glob("*.ipynb"):
        names.add(path.stem)
        if re.match(r"\d\d_", path.stem):
            names.add(path.stem[:3])
    assert names, "no notebook found"
    assert not [n for n in sorted(names) if n in source], [n for n in sorted(names) if n in source]


@pytest.mark.parametrize("path", sorted((ROOT / "notebooks").glob("[0-9][0-9]_*.ipynb")), ids=lambda p: p.stem)
def test_every_notebook_sets_up_through_the_shared_helper(path):
    cells = [c for c in json.loads(path.read_text())["cells"] if c["cell_type"] == "code"]
    assert "parameters" in cells[0]["metadata"].get("tags", [])
    setup = "".join(cells[1]["source"])
    assert "notebook.setup(profile, run_dir" in setup
    for pasted in ("seed must be", "case must be", "n_examples must be", "utils.runs_dir()", "resolve_run_dir"):
        assert pasted not in setup, pasted
