"""One name, one meaning: a public name (no leading underscore) is defined at the top level of one
module of the package. A name imported into another module is the same object, not a definition.

``SHARED`` lists the names still defined in two or more modules, each with why it stays for now
(most sit in modules that other work is changing this round, or are called by name from a
notebook's code). The test fails on a new name defined twice, and on a listed name no longer
defined twice, so the list only shrinks."""

import ast
from collections import defaultdict
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "geodepth_lite"

# name -> why it is still defined in more than one module
SHARED = {
    # the two pre-registered studies' parallel interfaces: reproduce and notebook 05 call them
    # module by module (study.py and reproduce.py are being changed beside this list)
    **{name: "study.py and study2.py: the two studies' parallel interface" for name in (
        "TESTS", "check_tables", "committed_dir", "family", "label", "read_tables", "score", "study_runs",
        "train", "write_tables")},
    "claims": "ablation, study, study2: each its own claims; notebook 05 calls all three",
    "DEPTH_TERMS": "losses.DEPTH_TERMS and study.DEPTH_TERMS (core/losses.py and study.py are being changed)",
    "MARKER": "book, gpu_check, train_many: each a different marker file (gpu_check.py, train_many.py "
              "are being changed)",
    "nearest_indices": "sdf and nnsearch, the nearest-point search in two modules (both being changed)",
    "nearest_indices_grid": "sdf and nnsearch_triton, the same search split (both being changed)",
    "term_gradient_norms": "losses and train (both being changed)",
    "intrinsics": "camera.intrinsics (principal point at W/2) and analytic.intrinsics ((W-1)/2); "
                  "gpu_check.py (being changed) calls analytic's",
    "is_complete": "integrity.is_complete (a dataset) and run_cache.is_complete (a run); reproduce.py "
                   "(being changed) calls run_cache's",
    "summary": "external.summary and gallery.summary: notebooks 06 and 07 call each by name",
}


def definitions(package: Path) -> dict[str, list[str]]:
    """Public top-level name -> the modules (dotted, under ``package``) that define it: a def, a
    class or an assignment (``X = ...``, ``X: T = ...``), not an import."""
    found = defaultdict(list)
    for path in sorted(package.rglob("*.py")):
        module = ".".join(path.relative_to(package.parent).with_suffix("").parts)
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                names = [node.name]
            elif isinstance(node, ast.Assign):
                names = [t.id for t in node.targets if isinstance(t, ast.Name)]
            elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
                names = [node.target.id]
            else:
                names = []
            for name in names:
                if not name.startswith("_") and module not in found[name]:
                    found[name].append(module)
    return dict(found)


def defined_twice(package: Path) -> dict[str, list[str]]:
    return {name: mods for name, mods in definitions(package).items() if len(mods) > 1}


def test_no_public_name_is_defined_in_two_modules_but_the_listed_ones():
    twice = defined_twice(PACKAGE)
    new = {name: mods for name, mods in twice.items() if name not in SHARED}
    assert not new, f"defined in more than one module (rename one, or import it from the other): {new}"
    gone = sorted(set(SHARED) - set(twice))
    assert not gone, f"no longer defined twice: take them off SHARED: {gone}"


def test_the_check_finds_a_name_defined_twice(tmp_path):
    """A package of two modules: a function and a constant defined in both are found; an imported
    name, a private one and a name defined once are not."""
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "a.py").write_text("LIMIT = 1\n_private = 1\n\ndef summary(rows):\n    return rows\n")
    (pkg / "b.py").write_text("from pkg.a import LIMIT\n_private = 2\nsummary: int = 3\n\n\nclass Other:\n    pass\n")
    (pkg / "c.py").write_text("LIMIT = 2\n")
    assert defined_twice(pkg) == {"LIMIT": ["pkg.a", "pkg.c"], "summary": ["pkg.a", "pkg.b"]}
