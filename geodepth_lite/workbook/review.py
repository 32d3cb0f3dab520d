"""A static review of the students' answer cells: constructs that no honest answer needs send the exercise
to manual grading, with the reason, instead of letting it score silently.

A student's answer runs in the same kernel as the exercise's checks, so it could reach what the checks
use: read their references out of the notebook's variables or the calling frames, turn the grading guard
off (:func:`geodepth_lite.workbook.grading.forbid`) or put back what it replaced, run a forbidden function in
another thread or process, rebuild it from the package's source, return a value that compares equal to
anything, or edit the kernel's input history that the checks run the answer from again. Each of these
needs a construct that the exercises never ask for (``inspect``, ``threading``, ``sys.setprofile``,
``exec``, ``In``, a class defining ``__eq__``, a ``%magic``, ``setattr`` taken as a value, a pickle, a module
that is not installed, a given input changed in place...). :data:`RULES` lists them, each with its
reason; :func:`review_cell` reads a cell's syntax tree (it never runs it) and returns a :class:`Finding`
per construct; ``course autograde`` calls :func:`review_notebook` on each graded submission, in the
grader's process: it reads every code cell the student could change, not only the answer cells.

A tripwire for a person, not a proof: a finding means "look at this answer", and an answer without one
may still be dishonest (the checks and the sandbox of :mod:`geodepth_lite.workbook.sandbox` are the other
defences). A cell that neither Python nor IPython can read is not reviewed: it runs nothing.
"""

from __future__ import annotations

import ast
import builtins
import contextlib
import functools
import importlib.machinery
import importlib.metadata
import inspect
import re
import sys
import types
from dataclasses import dataclass, replace

from geodepth_lite.workbook import exercises

RULES = {  # rule -> why no honest answer needs it (what the lecturer reads)
    "introspection": "reads the running program itself (frames, code objects, the garbage collector), where "
                     "the checks' references and code are",
    "concurrency": "runs code where the grading guard does not look (another thread, another process, the "
                   "shell, the network)",
    "dynamic-code": "builds or loads code at run time (exec, eval, compile, importlib, a pickle, which may call "
                    "any function), out of the reviewed text",
    "guard": "changes a module, the interpreter's hooks or an object made outside the answer: the grading "
             "guard's replacements live there",
    "kernel-history": "reads or edits the kernel's input history, from which the checks run the answer again",
    "namespace": "reads or writes the notebook's variables by name (globals(), vars(), builtins, __main__), "
                 "the checks' references among them",
    "check-names": "reads a variable that only the checks define (their inputs or reference values)",
    "special-method": "defines or borrows a special method (such as __eq__, __hash__, __bool__, __float__; "
                      "unittest.mock's ANY) that changes how the checks compare or convert the answer",
    "special-attribute": "reaches into objects through special attributes (__globals__, __dict__, __class__, "
                         "frames), where the checks' state is",
    "package-source": "reads the package's source files, to rebuild a function the exercise forbids",
    "grader-files": "names the grader's files (the course's solutions, gradebook or other submissions)",
    "shadowed-builtin": "rebinds a builtin (abs, float, isinstance...) in the notebook's namespace, where the "
                        "checks call it",
    "given-inputs": "changes the code the exercise gives, or the inputs it makes in place (the inputs from which "
                    "the checks compute their references)",
    "unreadable": "is too large or too deeply nested for the review to read: look at it by hand",
    "literal-answer": "writes out as a literal a value the exercise asks to compute (as a failed check's "
                      "message shows it)",
    "kernel": "reaches the IPython shell that runs the checks (get_ipython, its hooks, transformers or "
              "namespace), where a hook can change what every later check reports",
    "ipython": "uses IPython's own syntax (a %magic, a %%cell magic, a !shell line), which runs code the review "
               "cannot read",
    "missing-cell": "the exercise's answer cell is missing or lost its grading metadata, so its answer cannot be "
                    "reviewed where the checks expect it",
    "other-cells": "reads a variable that neither the notebook's own cells nor this answer cell define (a cell the "
                   "student added, another answer): the checks run this cell again under their guard, and a value "
                   "made in another cell escapes it",
    "earlier-run": "reads a variable before the cell sets it (``try: x`` / ``except NameError``): a value left by "
                   "the cell's first run, made unguarded, escapes the guard when the checks run the cell again",
    "module-value": "uses a module as a value (binds it to another name, puts it in a container, passes it to a "
                    "function): the review can no longer tell which of its functions the answer calls or replaces",
}
CELL_MAX_CHARS = 200_000  # a longer cell is not parsed but flagged (6 MB of `x = 1` lines: 2.4 GB to parse)
OWN_EXERCISE = {"literal-answer", "given-inputs", "check-names", "missing-cell", "other-cells",
                "earlier-run"}  # the other rules change the kernel
IPYTHON_CALLS = {"run_line_magic": "%", "run_cell_magic": "%%", "system": "!", "getoutput": "!"}

MODULES = {  # module (its first name) -> rule
    **dict.fromkeys(("inspect", "gc", "dis", "traceback", "pydoc", "ctypes", "trace", "tracemalloc",
                     "faulthandler"), "introspection"),
    **dict.fromkeys(("subprocess", "threading", "_thread", "multiprocessing", "concurrent", "asyncio", "pty",
                     "socket", "signal", "sched", "shlex"), "concurrency"),
    **dict.fromkeys(("importlib", "runpy", "code", "codeop", "marshal", "zipimport", "site", "pickle", "_pickle",
                     "copyreg", "shelve", "dill", "cloudpickle", "joblib"), "dynamic-code"),  # a pickle calls anything
    **dict.fromkeys(("builtins", "__main__", "__builtin__"), "namespace"),
    **dict.fromkeys(("IPython", "ipykernel", "jupyter_client"), "kernel-history"),
    "traitlets": "kernel",  # traitlets.config.Application.instance().shell is the kernel's shell
    **dict.fromkeys(("linecache", "pkgutil"), "package-source"),
    "unittest": "special-method",  # unittest.mock.ANY is equal to anything
}
SUBMODULES = {"multiprocessing": "concurrency", "threading": "concurrency", "subprocess": "concurrency"}
# a library's global hooks and operator tables: torch's register_module_forward_hook changes what every network
# computes, the checks' own too; torch.library replaces an operator everywhere; torch._C reaches both
GLOBAL_HOOKS = re.compile(r".*hook.*|library|_C", re.IGNORECASE)
OS_CALLS = re.compile(r"(system|popen|fork\w*|exec\w*|spawn\w*|posix_spawn\w*|kill\w*|_exit|startfile)")
SYS_ATTRIBUTES = {
    **dict.fromkeys(("setprofile", "settrace", "getprofile", "gettrace", "monitoring", "addaudithook",
                     "meta_path", "path_hooks", "setrecursionlimit"), "guard"),
    **dict.fromkeys(("_getframe", "_current_frames", "exc_info", "exception", "last_traceback"), "introspection"),
    "modules": "namespace",
}
BUILTINS = {**dict.fromkeys(("exec", "eval", "compile", "__import__"), "dynamic-code"),
            **dict.fromkeys(("globals", "vars", "locals"), "namespace"), "breakpoint": "introspection"}
ATTRIBUTE_BUILTINS = {"setattr": "guard", "delattr": "guard", "getattr": "special-attribute"}  # harmless only called
PICKLE = re.compile(r"pickle|safe_globals", re.IGNORECASE)  # pandas.read_pickle, torch's add_safe_globals...
CONTAINER_MUTATORS = {"append", "extend", "insert", "remove", "pop", "popitem", "clear", "update", "setdefault",
                      "add", "discard", "sort", "reverse"}
ARRAY_MUTATORS = {"fill", "put", "itemset", "resize", "setflags", "partition", "byteswap"}  # torch's end in "_"
FIRST_ARGUMENT_MUTATORS = {"copyto", "place", "putmask", "put_along_axis", "put"}  # numpy.copyto(CASE1, 0)
SHARING_CALLS = {"view", "reshape", "ravel", "squeeze", "unsqueeze", "swapaxes", "transpose", "permute", "expand",
                 "narrow", "asarray", "asanyarray", "as_strided", "from_numpy", "as_tensor", "values", "items"}
HISTORY_NAMES = re.compile(r"(In|Out|_ih|_oh|_dh|_i{1,3}|_i\d+|_\d+|get_ipython|__builtins__|__main__)")
KERNEL_NAMES = {"In", "Out", "_ih", "_oh", "_dh", "get_ipython", "__builtins__", "__main__"}  # even if assigned
FRAME_ATTRIBUTES = re.compile(r"(f_back|f_globals|f_locals|f_builtins|f_code|f_trace|tb_frame|tb_next|"
                              r"gi_frame|cr_frame|ag_frame|co_code|co_consts|co_names)")
KERNEL_ATTRIBUTES = {"get_ipython", "set_custom_exc", "input_transformers_post", "input_transformers_cleanup",
                     "ast_transformers", "user_ns", "user_global_ns", "register_magic_function", "run_cell",
                     "run_line_magic", "run_cell_magic", "history_manager", "showtraceback", "set_hook",
                     "events", "shell"}  # the shell's handles: attributes (ipywidgets.get_ipython), strings (getattr)
PLAIN_DUNDERS = {"__init__", "__name__", "__doc__", "__version__"}  # attributes an honest answer may use
PLAIN_METHODS = {"__init__", "__post_init__", "__repr__", "__str__"}  # methods an honest class may define
DUNDER = re.compile(r"__\w+__")
PACKAGE_PATH = re.compile(r"geodepth_lite\s*[/\\]|\.py\b")  # a path into the package, or any .py file
GRADER_PATH = re.compile(r"gradebook|\.ipynb\b|\b(source|submitted|autograded|release|feedback)[/\\]")


@dataclass(frozen=True)
class Finding:
    """One construct of a cell: its line, the rule and what was found; ``where``: the cell, when it is not
    the exercise's own answer cell."""
    line: int
    rule: str
    what: str
    where: str = ""

    def text(self) -> str:
        return f"{self.where + ', ' if self.where else ''}line {self.line}: {self.what}: {RULES[self.rule]}"


def _root_name(node: ast.AST) -> str | None:
    """The name an attribute chain starts from (``os`` of ``os.path.join``)."""
    while isinstance(node, (ast.Attribute, ast.Subscript, ast.Call)):
        node = node.func if isinstance(node, ast.Call) else node.value
    return node.id if isinstance(node, ast.Name) else None


def bound_names(tree: ast.AST) -> set[str]:
    """Every name a piece of code binds anywhere: assignments, parameters, functions, classes, imports."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Name) and isinstance(node.ctx, (ast.Store, ast.Del)):
            names.add(node.id)
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.arg):
            names.add(node.arg)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
        elif isinstance(node, ast.ExceptHandler) and node.name:
            names.add(node.name)
    return names


def _is_literal(node: ast.AST) -> bool:
    """A value written out in full: a number or string, or a container of them (None and empty ones are
    not: a released answer starts from those)."""
    def written(n):
        if isinstance(n, ast.Constant):
            return n.value is not None
        if isinstance(n, ast.UnaryOp) and isinstance(n.op, (ast.USub, ast.UAdd)):
            return written(n.operand)
        if isinstance(n, (ast.List, ast.Tuple, ast.Set)):
            return bool(n.elts) and all(written(e) for e in n.elts)
        if isinstance(n, ast.Dict):
            return bool(n.keys) and all(k is not None and written(k) and written(v) for k, v in zip(n.keys, n.values))
        return False

    return written(node)


def top_level_values(tree: ast.Module) -> dict[str, list[ast.AST]]:
    """name -> the values assigned to it outside any function or class (loops and branches included)."""
    out: dict[str, list[ast.AST]] = {}
    stack = list(tree.body)
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            continue
        if isinstance(node, (ast.Assign, ast.AnnAssign)) and node.value is not None:
            for target in (node.targets if isinstance(node, ast.Assign) else [node.target]):
                pairs = (zip(target.elts, node.value.elts) if isinstance(target, ast.Tuple) and isinstance(
                    node.value, ast.Tuple) and len(target.elts) == len(node.value.elts) else [(target, node.value)])
                for t, v in pairs:
                    for name in (n.id for n in ast.walk(t) if isinstance(n, ast.Name)):
                        out.setdefault(name, []).append(v if isinstance(t, ast.Name) else t)
        stack.extend(n for n in ast.iter_child_nodes(node) if isinstance(n, ast.stmt))
    return out


def _aliases(tree: ast.AST, earlier: dict[str, str] | None = None) -> dict[str, str]:
    """local name -> the module or module attribute it stands for (``o`` -> ``os`` after ``import os as o``,
    and after ``o = os`` or ``p = os.path``: a plain assignment passes the name on); ``os`` and ``sys`` stand
    for themselves where an earlier cell imported them, and so do the names in ``earlier`` (what the
    notebook's own cells import: :func:`notebook_imports`)."""
    out = {"os": "os", "sys": "sys", **(earlier or {})}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                out[a.asname or a.name.split(".")[0]] = a.name if a.asname else a.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.module:
            for a in node.names:
                out[a.asname or a.name] = f"{node.module}.{a.name}"
    passed = [(t.id, value) for t, value in _assignments(tree) if isinstance(t, ast.Name)]
    for _ in range(len(passed)):  # a chain of names (a = os; b = a) is passed on one link a round
        grown = {name: dotted for name, value in passed if name not in out
                 for dotted in [_dotted(value, out)] if dotted}
        if not grown:
            break
        out.update(grown)
    return out


def _assignments(tree: ast.AST) -> list[tuple[ast.expr, ast.expr]]:
    """(target, value) of each ``=``, annotated ``=`` and ``:=`` of a piece of code."""
    return [(t, n.value) for n in ast.walk(tree) if isinstance(n, (ast.Assign, ast.AnnAssign, ast.NamedExpr))
            and n.value is not None for t in (n.targets if isinstance(n, ast.Assign) else [n.target])]


def _written_getattr(node: ast.AST) -> bool:
    """``getattr(x, "name")`` or ``hasattr(x, "name")``: an attribute read under a name written in the cell."""
    return (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("getattr", "hasattr")
            and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant) and isinstance(node.args[1].value, str))


def _module_rule(dotted: str) -> str | None:
    """The rule a module (or a module's attribute, ``os.system``) falls under, if any."""
    parts = dotted.split(".")
    if parts[0] in MODULES:
        return MODULES[parts[0]]
    hit = next((SUBMODULES[p] for p in parts[1:] if p in SUBMODULES), None)
    if hit:
        return hit
    if any(GLOBAL_HOOKS.fullmatch(p) for p in parts[1:]):
        return "guard"
    if parts[0] == "os" and len(parts) > 1 and OS_CALLS.fullmatch(parts[1]):
        return "concurrency"
    if parts[0] == "sys" and len(parts) > 1:
        return SYS_ATTRIBUTES.get(parts[1])
    return None


def _dotted(node: ast.AST, aliases: dict[str, str]) -> str | None:
    """``os.system`` for ``o.system`` after ``import os as o``, and for ``getattr(o, "system")``; None for
    anything but a name's attributes."""
    parts = []
    while isinstance(node, ast.Attribute) or _written_getattr(node):
        parts.append(node.attr if isinstance(node, ast.Attribute) else node.args[1].value)
        node = node.value if isinstance(node, ast.Attribute) else node.args[0]
    if not isinstance(node, ast.Name) or node.id not in aliases:
        return None
    return ".".join([aliases[node.id], *reversed(parts)])


@functools.cache
def installed_modules() -> frozenset[str]:
    """The modules an answer may import: Python's own and the top-level ones of the installed distributions.
    Any other is a file beside the notebook, which the notebook itself may have written, out of the review."""
    return frozenset({*sys.stdlib_module_names, *sys.builtin_module_names, "geodepth_lite",
                      *importlib.metadata.packages_distributions()})


@functools.cache
def names_module(dotted: str) -> bool:
    """Whether ``dotted`` names a module: ``numpy``, ``os.path``, ``geodepth_lite.workbook.grading``, or a
    module another one holds (``geodepth_lite.evaluation.ablation.np``). Read from the modules the grader has
    loaded (the package's own are imported for it; attributes are read as they are stored, running no
    code) and, past those, from the installed files, found without running them."""
    parts = dotted.split(".")
    if any(DUNDER.fullmatch(p) or not p.isidentifier() for p in parts):
        return False  # __main__ and its kin are flagged by name, and never imported here; no path is looked up
    found, locations = None, None  # what the name reached so far; where its submodules' files lie
    for depth, part in enumerate(parts):
        prefix = ".".join(parts[: depth + 1])
        if prefix.split(".")[0] == "geodepth_lite" and (depth == 0 or isinstance(found, types.ModuleType)):
            with contextlib.suppress(Exception):  # one that cannot be imported here is read from its file
                importlib.import_module(prefix)  # the package's own modules run nothing when imported
        if prefix in sys.modules:
            found = sys.modules[prefix]
        elif isinstance(found, types.ModuleType) and inspect.getattr_static(found, part, None) is not None:
            found = inspect.getattr_static(found, part)
        elif depth == 0 or locations:
            found = importlib.machinery.PathFinder.find_spec(part, locations)  # a file, not loaded
            if found is None:
                return False
        else:
            return False
        spec = found if isinstance(found, importlib.machinery.ModuleSpec) else getattr(found, "__spec__", None)
        locations = getattr(spec, "submodule_search_locations", None) if isinstance(
            found, (types.ModuleType, importlib.machinery.ModuleSpec)) else None
    return isinstance(found, (types.ModuleType, importlib.machinery.ModuleSpec))


def _local_imports(node: ast.Import | ast.ImportFrom) -> list[str]:
    """The modules ``node`` imports that are not installed (a relative import is never installed)."""
    names = [a.name for a in node.names] if isinstance(node, ast.Import) else [
        "." * node.level + (node.module or "")]
    return [n for n in names if n.startswith(".") or n.split(".")[0] not in installed_modules()]


def _import_findings(tree: ast.AST, aliases: dict[str, str]) -> list[Finding]:
    found = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            found += [Finding(node.lineno, "dynamic-code", f"import {n} (not installed: a file beside the notebook)")
                      for n in _local_imports(node)]
        if isinstance(node, ast.Import):
            found += [Finding(node.lineno, rule, f"import {a.name}") for a in node.names
                      for rule in [_module_rule(a.name)] if rule]
        elif isinstance(node, ast.ImportFrom) and node.module:
            rule = _module_rule(node.module)
            if rule:
                found.append(Finding(node.lineno, rule, f"from {node.module} import ..."))
                continue
            found += [Finding(node.lineno, r, f"from {node.module} import {a.name}") for a in node.names
                      for r in [_module_rule(f"{node.module}.{a.name}")] if r]
        elif (isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Load)) or _written_getattr(node):
            dotted = _dotted(node, aliases)
            rule = _module_rule(dotted) if dotted and "." in dotted else None
            if rule:
                found.append(Finding(node.lineno, rule, dotted))
    return found


def _call_findings(tree: ast.AST, own: set[str], aliases: dict[str, str]) -> list[Finding]:
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        name = node.func.id if isinstance(node.func, ast.Name) else None
        for kw in node.keywords:  # numpy.load(allow_pickle=True), torch.load(weights_only=False) unpickle
            lets = not (isinstance(kw.value, ast.Constant) and kw.value.value is (kw.arg == "weights_only"))
            if kw.arg and (PICKLE.search(kw.arg) or kw.arg == "weights_only") and lets:
                found.append(Finding(node.lineno, "dynamic-code", f"{kw.arg}={ast.unparse(kw.value)[:20]}"))
        if name in ("getattr", "setattr", "delattr", "hasattr") and len(node.args) >= 2:
            attr = node.args[1]
            if not (isinstance(attr, ast.Constant) and isinstance(attr.value, str)):
                found.append(Finding(node.lineno, "special-attribute", f"{name}() of an attribute named at run time"))
            elif name in ("setattr", "delattr") and _outside(node.args[0], own, aliases):
                found.append(Finding(node.lineno, "guard", f"{name}() on {ast.unparse(node.args[0])}"))
        if name == "open" or (isinstance(node.func, ast.Attribute) and node.func.attr in (
                "read_text", "read_bytes", "open", "loadtxt", "fromfile")):
            text = " ".join(ast.unparse(a) for a in (*node.args, node.func))
            if PACKAGE_PATH.search(text) or "__file__" in text or "__spec__" in text:
                found.append(Finding(node.lineno, "package-source", f"reading {ast.unparse(node)[:60]}"))
    return found


def _outside(node: ast.AST, own: set[str], aliases: dict[str, str]) -> bool:
    """Whether an expression starts from a module or from a name the answer cell did not make."""
    root = _root_name(node)
    return root is not None and (root in aliases or root not in own)


def _docstrings(tree: ast.AST) -> set[int]:
    """The ids of the strings that stand alone as statements (docstrings): text no code uses."""
    return {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant)}


def _builtin_findings(tree: ast.AST) -> list[Finding]:
    """The builtins that run code or reach any attribute: called, or taken as a value (``s = setattr``,
    ``map(setattr, ...)``, ``f = eval``), where the review no longer sees what they are given. A name the
    cell binds itself counts too: ``setattr = setattr`` is still the builtin."""
    callees = {id(n.func) for n in ast.walk(tree) if isinstance(n, ast.Call)}
    found = []
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Name) and isinstance(node.ctx, ast.Load)):
            continue
        called = id(node) in callees
        if node.id in BUILTINS:
            found.append(Finding(node.lineno, BUILTINS[node.id], f"{node.id}()" if called else
                                 f"{node.id} taken as a value"))
        elif node.id in ATTRIBUTE_BUILTINS and not called:
            found.append(Finding(node.lineno, ATTRIBUTE_BUILTINS[node.id], f"{node.id} taken as a value"))
    found += [Finding(n.lineno, "namespace", "dir() of the notebook's variables") for n in ast.walk(tree)
              if isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id == "dir" and not n.args]
    return found


def _name_findings(tree: ast.AST, own: set[str], check_names: set[str]) -> list[Finding]:
    found = []
    prose = _docstrings(tree)
    for node in ast.walk(tree):
        if isinstance(node, ast.Name):
            if HISTORY_NAMES.fullmatch(node.id) and (node.id in KERNEL_NAMES or node.id not in own):
                rule = "namespace" if node.id in ("__builtins__", "__main__") else "kernel-history"
                found.append(Finding(node.lineno, rule, node.id))
            elif node.id in check_names and node.id not in own and isinstance(node.ctx, ast.Load):
                found.append(Finding(node.lineno, "check-names", node.id))
        elif isinstance(node, ast.Attribute):
            if PICKLE.search(node.attr):
                found.append(Finding(node.lineno, "dynamic-code", f".{node.attr}"))
            elif (DUNDER.fullmatch(node.attr) and node.attr not in PLAIN_DUNDERS) or FRAME_ATTRIBUTES.fullmatch(
                    node.attr):
                found.append(Finding(node.lineno, "special-attribute", f".{node.attr}"))
            elif node.attr in KERNEL_ATTRIBUTES:
                found.append(Finding(node.lineno, "kernel", f".{node.attr}"))
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in prose:
            if DUNDER.fullmatch(node.value) and node.value not in PLAIN_DUNDERS:
                found.append(Finding(node.lineno, "special-attribute", repr(node.value)))
            elif node.value in KERNEL_ATTRIBUTES:
                found.append(Finding(node.lineno, "kernel", repr(node.value)))
            elif PACKAGE_PATH.search(node.value):
                found.append(Finding(node.lineno, "package-source", repr(node.value[:60])))
            elif GRADER_PATH.search(node.value):
                found.append(Finding(node.lineno, "grader-files", repr(node.value[:60])))
    return found


def _class_findings(tree: ast.AST) -> list[Finding]:
    found = []
    for cls in (n for n in ast.walk(tree) if isinstance(n, ast.ClassDef)):
        if any(k.arg == "metaclass" for k in cls.keywords):
            found.append(Finding(cls.lineno, "special-method", f"class {cls.name} with a metaclass"))
        for node in cls.body:
            targets = getattr(node, "targets", [getattr(node, "target", None)])
            names = ([node.name] if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) else
                     [t.id for t in targets if isinstance(t, ast.Name)])
            found += [Finding(node.lineno, "special-method", f"class {cls.name} defines {n}") for n in names
                      if DUNDER.fullmatch(n) and n not in PLAIN_METHODS]
    return found


def _module_value_findings(tree: ast.AST, aliases: dict[str, str]) -> list[Finding]:
    """Modules used other than through their attributes (``m = grading``, ``[ablation, sys]``, ``f(grading)``,
    ``for m in [sys]``, ``p = np.random``): past that point the review's rules, which read ``sys.setprofile``
    or ``grading.forbid = ...`` by the module's name, no longer see what is done with it."""
    parents = {id(child): node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
    found = []
    for node in ast.walk(tree):
        if not ((isinstance(node, (ast.Name, ast.Attribute)) and isinstance(node.ctx, ast.Load))
                or _written_getattr(node)):
            continue
        parent = parents.get(id(node))
        if ((isinstance(parent, ast.Attribute) and parent.value is node) or (isinstance(parent, ast.Call) and (
                parent.func is node or (_written_getattr(parent) and parent.args[0] is node)))):
            continue  # read through its attributes (``m.f``, ``getattr(m, "f")``), or called
        dotted = _dotted(node, aliases)
        if dotted and names_module(dotted):
            found.append(Finding(node.lineno, "module-value", f"{ast.unparse(node)[:60]} (the module {dotted})"))
    return found


def _made_names(tree: ast.AST) -> set[str]:
    """The names the cell binds only to objects it makes: what a call returns, a literal or comprehension, a
    function or class it defines, and ``self`` (the first parameter of a method of one of its classes, but a
    static one). A name also bound to anything else (another name, an attribute or item, a loop's element, a
    function's argument) may stand for a module or for an object made elsewhere, such as the checks'."""
    made_values = (ast.Call, ast.Constant, ast.List, ast.Tuple, ast.Set, ast.Dict, ast.ListComp, ast.SetComp,
                   ast.DictComp, ast.GeneratorExp, ast.Lambda, ast.JoinedStr, ast.BinOp, ast.UnaryOp, ast.Compare)
    made_sites = {id(t) for t, value in _assignments(tree) if isinstance(value, made_values)}
    made_sites |= {id(n.target) for n in ast.walk(tree) if isinstance(n, ast.AugAssign)}  # x += ... keeps x's kind
    for cls in (n for n in ast.walk(tree) if isinstance(n, ast.ClassDef)):
        for fn in (n for n in cls.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))):
            static = any(isinstance(d, ast.Name) and d.id == "staticmethod" for d in fn.decorator_list)
            if fn.args.args and not static:
                made_sites.add(id(fn.args.args[0]))
    made, other = set(), set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            made.add(node.name)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            (made if id(node) in made_sites else other).add(node.id)
        elif isinstance(node, ast.arg):
            (made if id(node) in made_sites else other).add(node.arg)
        elif isinstance(node, ast.ExceptHandler) and node.name:
            other.add(node.name)
        elif isinstance(node, (ast.MatchAs, ast.MatchStar)) and node.name:
            other.add(node.name)
    return made - other


def _write_findings(tree: ast.AST, own: set[str], aliases: dict[str, str]) -> list[Finding]:
    """Attributes set or deleted on a module or on an object the answer did not make (``own``: the names it
    binds only to objects it makes), and a module's tables changed in place (``ablation.PAPER_REDUCTION.clear()``,
    or under a name that stands for it: ``table = ablation.PAPER_REDUCTION``, then ``table.clear()``)."""
    found = []
    for node in ast.walk(tree):
        call = node.func if isinstance(node, ast.Call) else None
        if (isinstance(call, ast.Attribute) and call.attr in CONTAINER_MUTATORS
                and ((isinstance(call.value, (ast.Attribute, ast.Subscript)) and _outside(call.value, own - set(
                    aliases), aliases)) or (isinstance(call.value, ast.Name) and call.value.id in aliases
                                                       and not names_module(aliases[call.value.id])))):
            found.append(Finding(node.lineno, "guard", f"{ast.unparse(call.value)[:60]} changed in place"))
        if isinstance(node, (ast.Attribute, ast.Subscript)) and isinstance(node.ctx, (ast.Store, ast.Del)):
            if isinstance(node, ast.Subscript) and not isinstance(node.value, ast.Attribute):
                continue  # an item of a list or dict: only an attribute's items (``mod.table[k] = ...``) count
            if _outside(node.value, own - set(aliases), aliases):
                found.append(Finding(node.lineno, "guard", f"{ast.unparse(node)} changed"))
    return found


def _literal_findings(tree: ast.Module, computed: set[str]) -> list[Finding]:
    found = []
    for name, values in top_level_values(tree).items():
        if name in computed:
            found += [Finding(v.lineno, "literal-answer", f"{name} = {ast.unparse(v)[:50]}") for v in values
                      if _is_literal(v)]
    return found


def module_scope(tree: ast.Module) -> list[ast.stmt]:
    """The statements that run in the notebook's namespace: the cell's top level, with the bodies of its
    loops, branches, ``with`` and ``try`` blocks, but not of functions or classes."""
    out, stack = [], list(reversed(tree.body))
    while stack:
        node = stack.pop()
        out.append(node)
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            stack.extend(reversed([n for n in ast.iter_child_nodes(node) if isinstance(n, (ast.stmt,
                                                                                          ast.excepthandler))]))
    return [n for n in out if isinstance(n, ast.stmt)]


def _scope_walk(node: ast.AST):
    """The nodes of ``node`` that run in its own scope: not inside a function, lambda, class or comprehension
    it holds (those bind and read their own names)."""
    yield node
    if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda, ast.ClassDef, ast.ListComp,
                             ast.SetComp, ast.DictComp, ast.GeneratorExp)):
        for child in ast.iter_child_nodes(node):
            yield from _scope_walk(child)


def _earlier_run_findings(tree: ast.Module, earlier: set[str]) -> list[Finding]:
    """A name read in a scope before that scope first sets it (the cell's top level, or a function for the
    names it declares ``global``), unless the notebook's own cells set it (``earlier``); and any mention of
    ``NameError`` or ``UnboundLocalError``. Either tests whether an earlier run of the cell left a value."""
    found = [Finding(n.lineno, "earlier-run", n.id) for n in ast.walk(tree)
             if isinstance(n, ast.Name) and n.id in ("NameError", "UnboundLocalError")]
    scopes = [(tree, None)] + [(fn, {g for st in ast.walk(fn) if isinstance(st, ast.Global) for g in st.names})
                               for fn in ast.walk(tree) if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef))]
    for scope, names in scopes:
        ends = {}  # a name's node -> where the simple statement that holds it ends (its value is set then)
        body = []
        for st in scope.body:
            for n in _scope_walk(st):
                body.append(n)
                if isinstance(n, ast.stmt) and not isinstance(n, COMPOUND):
                    ends.update((id(m), (n.end_lineno, n.end_col_offset)) for m in _scope_walk(n))
        first: dict[str, tuple] = {}
        for n in body:
            if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store):
                at = ends.get(id(n), (n.end_lineno, n.end_col_offset))  # a loop's or with's name: set where it is
                first[n.id] = min(first.get(n.id, at), at)
        found += [Finding(n.lineno, "earlier-run", f"{n.id} read before the cell sets it") for n in body
                  if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Load) and n.id in first and n.id not in earlier
                  and (names is None or n.id in names) and (n.lineno, n.col_offset) < first[n.id]]
    return found


COMPOUND = (ast.If, ast.For, ast.AsyncFor, ast.While, ast.With, ast.AsyncWith, ast.Try, ast.FunctionDef,
            ast.AsyncFunctionDef, ast.ClassDef, ast.Match)


def _other_cell_findings(tree: ast.Module, notebook_names: set[str]) -> list[Finding]:
    """Names the cell reads that neither it nor the notebook's own cells set (nor Python's builtins, nor the
    ``display`` IPython adds to them)."""
    bound = bound_names(tree) | notebook_names | BUILTIN_NAMES | KERNEL_NAMES | {"__name__", "__doc__", "display"}
    return [Finding(n.lineno, "other-cells", n.id) for n in ast.walk(tree)
            if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Load) and n.id not in bound]


def _scope_names(node: ast.stmt) -> set[str]:
    """The names one statement binds (or changes in place: ``x[0] = 1``) in the namespace it runs in."""
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        return {node.name}
    if isinstance(node, (ast.Import, ast.ImportFrom)):
        return {(a.asname or a.name).split(".")[0] for a in node.names}
    targets = {ast.Assign: lambda n: n.targets, ast.AugAssign: lambda n: [n.target], ast.AnnAssign: lambda n: [
        n.target], ast.For: lambda n: [n.target], ast.Delete: lambda n: n.targets,
               ast.With: lambda n: [i.optional_vars for i in n.items if i.optional_vars is not None]}
    found = set()
    for target in targets.get(type(node), lambda n: [])(node):
        found |= {_root_name(target)} - {None} | {n.id for n in ast.walk(target) if isinstance(n, ast.Name)
                                                  and isinstance(n.ctx, (ast.Store, ast.Del))}
    return found


BUILTIN_NAMES = frozenset(n for n in dir(builtins) if not n.startswith("_"))


def _shadow_findings(tree: ast.Module, called: frozenset[str]) -> list[Finding]:
    return [Finding(node.lineno, "shadowed-builtin", f"{name} rebound") for node in module_scope(tree)
            for name in sorted(_scope_names(node) & called)]


def builtins_read(check_sources) -> frozenset[str]:
    """The builtins the check cells use (``abs``, ``float``, ``isinstance``...): those an answer must not
    rebind in the namespace it shares with them."""
    read = set()
    for src in check_sources:
        try:
            read |= {n.id for n in ast.walk(ast.parse(src)) if isinstance(n, ast.Name)}
        except (SyntaxError, ValueError):
            continue
    return frozenset(read & BUILTIN_NAMES)


def released(answer: str) -> str:
    """An answer cell as the release gives it: each solution region replaced by ``raise NotImplementedError()``."""
    out, inside = [], False
    for line in answer.splitlines():
        if line.strip() == exercises.SOLUTION_MARKERS[0]:
            out.append(line[: len(line) - len(line.lstrip())] + "raise NotImplementedError()")
            inside = True
        elif line.strip() == exercises.SOLUTION_MARKERS[1]:
            inside = False
        elif not inside:
            out.append(line)
    return "\n".join(out)


def given_inputs(answer: str, check: str) -> dict[str, list[str]]:
    """input name -> the given statements (``ast.dump``) that bind it: the names the released answer cell binds
    in the notebook's namespace with a value (not the ``None`` a student replaces, not a function left to
    write, not an import) and the check reads without making them itself."""
    try:
        check_tree = ast.parse(check)
        read = {n.id for n in ast.walk(check_tree) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Load)}
        read -= bound_names(check_tree)  # what the check makes itself is no input
        statements = module_scope(ast.parse(released(answer)))
    except (SyntaxError, ValueError):
        return {}
    out: dict[str, list[str]] = {}
    for node in statements:
        stub = any(isinstance(n, ast.Raise) and "NotImplementedError" in ast.unparse(n) for n in ast.walk(node))
        if stub or isinstance(node, (ast.Import, ast.ImportFrom)) or (isinstance(node, ast.Assign) and _is_empty(
                node.value)) or (
                isinstance(node, ast.Assign) and isinstance(node.value, ast.Tuple) and all(
                _is_empty(e) or (isinstance(e, ast.Constant) and e.value == "") for e in node.value.elts)):
            continue
        for name in _scope_names(node) & read:
            out.setdefault(name, []).append(ast.dump(node))
    return out


def _given_findings(tree: ast.Module, given: dict[str, list[str]]) -> list[Finding]:
    found = []
    kept = {ast.dump(n) for n in module_scope(tree)}
    for node in module_scope(tree):
        changed = sorted(n for n in _scope_names(node) & set(given) if ast.dump(node) not in given[n])
        found += [Finding(node.lineno, "given-inputs", f"{name} changed") for name in changed]
    found += [Finding(line, "given-inputs", f"{name} changed in place") for line, name in _in_place(tree, set(given))]
    for name, statements in sorted(given.items()):
        if not set(statements) <= kept:
            found.append(Finding(1, "given-inputs", f"the given lines that set {name} are not all there"))
    return found


def _bindings(tree: ast.AST) -> list[tuple[ast.expr, ast.expr]]:
    """(value, name) for every name the cell binds to a value: ``=``, an annotated one, ``:=``, and a
    loop's or comprehension's names (the value then is what they run over)."""
    return [(value, t) for t, value in _assignments(tree)] + [
        (node.iter, n) for node in ast.walk(tree) if isinstance(node, (ast.For, ast.AsyncFor, ast.comprehension))
        for n in ast.walk(node.target) if isinstance(n, ast.Name)]


def _in_place(tree: ast.AST, given: set[str]) -> list[tuple[int, str]]:
    """(line, name) where code anywhere in the cell, functions included, changes one of ``given`` in place:
    an item or attribute set or deleted (``edits["a"] = 1``), a mutating method (``edits.clear()``,
    ``CASE1.fill(0)``, torch's ``x.zero_()``), a function that changes its first argument (``dict.clear(edits)``,
    ``np.copyto(CASE1, 0)``, ``torch.relu_(x)``), a function of the cell's own that changes the argument
    (``def wipe(d): d.clear()`` then ``wipe(edits)``), or an ``out=`` array."""
    names = set(given)
    mutating = _mutating_functions(tree)

    def named(node):  # the name whose own object this is: a part of it (``edits["a"]``), a view of its memory
        while True:   # (``CASE1.reshape(-1)``, ``np.asarray(CASE1)``), never a copy (``CASE1.copy()``)
            if isinstance(node, (ast.Attribute, ast.Subscript, ast.NamedExpr)):
                node = node.value
            elif (isinstance(node, ast.Call) and isinstance(node.func, (ast.Attribute, ast.Name))
                  and (node.func.attr if isinstance(node.func, ast.Attribute) else node.func.id) in SHARING_CALLS):
                node = node.func.value if isinstance(node.func, ast.Attribute) and named(
                    node.func.value) else (node.args[0] if node.args else None)
            else:
                return node.id if isinstance(node, ast.Name) and node.id in names else None

    origin = {name: name for name in names}  # and the names bound to them, by the given name they stand for
    while True:  # (``e = edits``, ``row = edits["a"]``, ``for v in edits.values()``)
        more = {t.id: origin[named(value)] for value, t in _bindings(tree)
                if named(value) and isinstance(t, ast.Name) and t.id not in names}
        if not more:
            break
        names |= set(more)
        origin.update(more)
    out = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.Attribute, ast.Subscript)) and isinstance(node.ctx, (ast.Store, ast.Del)):
            out.append((node.lineno, named(node)))
        elif isinstance(node, ast.Call) and isinstance(node.func, (ast.Attribute, ast.Name)):
            method = node.func.attr if isinstance(node.func, ast.Attribute) else node.func.id
            trailing = method.endswith("_") and not method.startswith("_")  # torch: x.zero_(), torch.relu_(x)
            if isinstance(node.func, ast.Attribute) and (method in CONTAINER_MUTATORS | ARRAY_MUTATORS or trailing):
                out.append((node.lineno, named(node.func.value)))
            unbound = isinstance(node.func, ast.Attribute) and _root_name(node.func) in ("dict", "list", "set")
            if (unbound and method in CONTAINER_MUTATORS) or method in FIRST_ARGUMENT_MUTATORS or trailing:
                out += [(node.lineno, named(a)) for a in node.args[:1]]
            spots = mutating.get(method, set()) if isinstance(node.func, ast.Name) else set()
            out += [(node.lineno, named(a)) for i, a in enumerate(node.args) if i in spots]
            out += [(node.lineno, named(kw.value)) for kw in node.keywords if kw.arg == "out" or kw.arg in spots]
    return [(line, origin[name]) for line, name in out if name in names]


def _mutating_functions(tree: ast.AST) -> dict[str, set]:
    """function name -> the positions and names of its parameters that it changes in place, for each function
    the code defines inside ``tree`` (``def wipe(d): d.clear()`` -> ``{0, "d"}``)."""
    out = {}
    for fn in ast.walk(tree):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)) and fn is not tree:
            params = [*fn.args.posonlyargs, *fn.args.args]
            own = {a.arg for a in [*params, *fn.args.kwonlyargs]}
            changed = {name for _, name in _in_place(fn, own)} & own
            out[fn.name] = changed | {i for i, a in enumerate(params) if a.arg in changed}
    return out


def parse_cell(source: str) -> tuple[ast.Module, list[Finding]]:
    """A cell's syntax tree as the kernel runs it: the Python itself or, where it is not Python, the Python
    IPython turns it into (``%magic`` becomes ``get_ipython().run_line_magic(...)``), with a finding for each
    magic or shell line. Raises SyntaxError where IPython cannot read it either: such a cell runs nothing."""
    try:
        return ast.parse(source), []
    except SyntaxError:
        from IPython.core.inputtransformer2 import TransformerManager  # heavy: only for a cell that needs it

        tree = ast.parse(TransformerManager().transform_cell(source))
    found = []
    for node in ast.walk(tree):
        call = node.func if isinstance(node, ast.Call) else None
        if (isinstance(call, ast.Attribute) and call.attr in IPYTHON_CALLS and isinstance(call.value, ast.Call)
                and isinstance(call.value.func, ast.Name) and call.value.func.id == "get_ipython"):
            first = node.args[0] if node.args else None
            name = first.value if isinstance(first, ast.Constant) and isinstance(first.value, str) else "?"
            found.append(Finding(node.lineno, "ipython", IPYTHON_CALLS[call.attr] + name[:40]))
    return tree, found


def notebook_imports(sources) -> dict[str, str]:
    """name -> the module or module attribute that the notebook's own code cells (``sources``) import under
    it: in the kernel, an answer finds ``np`` or ``ablation`` bound there without importing them itself."""
    out = {}
    for src in sources:
        try:
            tree = ast.parse(src)
        except (SyntaxError, ValueError, RecursionError, MemoryError):
            continue
        out.update({k: v for k, v in _aliases(tree).items() if k in bound_names(tree)})
    return out


def review_cell(source: str, *, check_names=(), computed=(), given=None, shadowed=BUILTIN_NAMES,
                earlier=None, notebook_names=None, notebook_objects=()) -> list[Finding]:
    """The findings of one answer cell, by line (empty: nothing to look at). ``check_names``: variables only
    the checks define (:func:`check_only_names`); ``computed``: answer variables the exercise's solution
    computes rather than writes out (:func:`computed_names`); ``given``: the inputs the answer cell gives
    (:func:`given_inputs`); ``shadowed``: the builtins it must not rebind (:func:`builtins_read`);
    ``earlier``: the modules the notebook's own cells import (:func:`notebook_imports`); ``notebook_names``:
    the names the notebook's own cells set (given for an answer cell, which the checks run again: a read of
    any other name, or of one before the cell sets it, is a finding; None: neither is read);
    ``notebook_objects``: the same names, whose objects no cell of the student's may change in place (a
    value kept there escapes the checks' guard as in another variable).
    IPython's
    own syntax is read as the kernel reads it (:func:`parse_cell`)."""
    if len(source) > CELL_MAX_CHARS:
        return [Finding(1, "unreadable", f"the whole cell ({len(source):,} characters, more than the "
                                         f"{CELL_MAX_CHARS:,} the review reads)")]
    try:
        tree, magic = parse_cell(source)
        own, made = bound_names(tree), _made_names(tree)
        aliases = _aliases(tree, {k: v for k, v in (earlier or {}).items() if k not in own})
        found = (_import_findings(tree, aliases) + _call_findings(tree, made, aliases)
                 + _builtin_findings(tree) + _name_findings(tree, own, set(check_names)) + _class_findings(tree)
                 + _write_findings(tree, made, aliases) + _module_value_findings(tree, aliases)
                 + [Finding(line, "guard", f"{name} changed in place (an object of the notebook's own cells)")
                    for line, name in _in_place(tree, set(notebook_objects) - own - set(given or {}))]
                 + (_earlier_run_findings(tree, set(notebook_names)) + _other_cell_findings(
                     tree, set(notebook_names)) if notebook_names is not None else [])
                 + _literal_findings(tree, set(computed))
                 + _shadow_findings(tree, frozenset(shadowed)) + _given_findings(tree, given or {}))
        magic_lines = {f.line for f in magic}  # there the get_ipython() is IPython's: said once, as the magic
        found = magic + [f for f in found if not (f.line in magic_lines and f.what == "get_ipython")]
    except (SyntaxError, ValueError):
        return []  # neither Python nor IPython: the cell stops at once when it runs, and scores nothing
    except (RecursionError, MemoryError):  # Python's own parser gives up on it too
        return [Finding(1, "unreadable", "the whole cell")]
    unique = {(f.line, f.rule, f.what): f for f in found}
    return sorted(unique.values(), key=lambda f: (f.line, f.rule, f.what))


def _names_bound(source: str) -> set[str]:
    """The names a cell's code binds (none where Python cannot read it)."""
    try:
        return bound_names(ast.parse(source))
    except (SyntaxError, ValueError, RecursionError, MemoryError):
        return set()


def check_only_names(check_sources, other_sources) -> set[str]:
    """Names the check cells bind that no other cell of the notebook does (lessons, answers)."""
    return set().union(*map(_names_bound, check_sources)) - set().union(*map(_names_bound, other_sources))


def computed_names(solution: str, check: str) -> set[str]:
    """The variables the check reads that the exercise's solution (its answer cell) assigns at top level with
    anything but a written-out value: the values the exercise asks the student to compute."""
    try:
        values = top_level_values(ast.parse(solution))
        read = {n.id for n in ast.walk(ast.parse(check)) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Load)}
    except (SyntaxError, ValueError):
        return set()
    return {name for name, vs in values.items()
            if name in read and not all(_is_literal(v) or _is_empty(v) for v in vs)}


def _is_empty(node: ast.AST) -> bool:
    return (isinstance(node, ast.Constant) and node.value is None) or (
        isinstance(node, (ast.List, ast.Tuple, ast.Set, ast.Dict)) and not getattr(node, "elts", getattr(
            node, "keys", None)))


def review_notebook(source: dict, submitted: dict) -> dict[str, list[Finding]]:
    """exercise id -> its findings, for each exercise of ``submitted`` (a returned notebook's JSON) that has
    any, in notebook order. ``source``: the same notebook with its solutions (the course's ``source/``),
    which says what only the checks define and what the solutions compute.

    Every code cell runs in the kernel that later runs the checks, so every one is read: each exercise's
    answer cell as its answer, and every other code cell that is not one of the notebook's own, unchanged (a
    cell the student added or edited, an answer cell without its grading metadata). A finding that changes
    the kernel (all rules but :data:`OWN_EXERCISE`) is also given to every exercise whose check runs after
    it; an exercise whose answer cell is missing gets a ``missing-cell`` finding."""
    reference = exercises.notebook_exercises(source)
    check_cells = [id(ex.cells["check"]) for ex in reference.values() if "check" in ex.cells]
    others = ["".join(c.get("source", "")) for c in source["cells"]  # a list of lines, or one string
              if c.get("cell_type") == "code" and id(c) not in check_cells]
    given = {*others, *(exercises.visible_check(ex.check) for ex in reference.values()),
             *(released(ex.answer) for ex in reference.values())}  # a check or a stub run again is no finding
    context = {"check_names": check_only_names([ex.check for ex in reference.values()], others),
               "earlier": notebook_imports(["".join(c.get("source", "")) for c in source["cells"]
                                            if c.get("cell_type") == "code"]),
               "shadowed": builtins_read(ex.check for ex in reference.values())}
    answer_cells = {id(ex.cells["answer"]) for ex in reference.values() if "answer" in ex.cells}
    own_names = set().union(*map(_names_bound, [  # by the notebook's own cells: an answer's stub, not its solution
        *("".join(c.get("source", "")) for c in source["cells"] if c.get("cell_type") == "code"
          and id(c) not in answer_cells), *(released(ex.answer) for ex in reference.values() if "answer" in ex.cells)]))
    mine = {ident: ex for ident, ex in exercises.notebook_exercises(submitted).items() if ident in reference}
    answer_of = {id(ex.cells["answer"]): ident for ident, ex in mine.items() if "answer" in ex.cells}
    check_of = {id(ex.cells["check"]): ident for ident, ex in mine.items() if "check" in ex.cells}
    out: dict[str, list[Finding]] = {}
    carried: list[tuple[str | None, Finding]] = []  # (the exercise whose answer it is in, the finding)
    for position, cell in enumerate(submitted["cells"], 1):
        text = "".join(cell.get("source", ""))
        if cell.get("cell_type") != "code":
            continue
        if id(cell) in check_of:
            ident = check_of[id(cell)]
            out.setdefault(ident, []).extend(f for origin, f in carried if origin != ident)
        elif id(cell) in answer_of:
            ident = answer_of[id(cell)]
            found = _answer_findings(reference[ident], text, {**context, "notebook_names": own_names,
                                                              "notebook_objects": own_names})
            out.setdefault(ident, []).extend(found)
            where = f"in the answer cell of exercise {ident.replace('-', '.')}"
            carried += [(ident, replace(f, where=where)) for f in found if f.rule not in OWN_EXERCISE]
        elif text not in given:
            where = f"in code cell {position}, added or changed by the student"
            carried += [(None, replace(f, where=where)) for f in review_cell(text, notebook_objects=own_names,
                                                                             **context)]
    for ident, ex in reference.items():
        if "answer" in ex.cells and "answer" not in getattr(mine.get(ident), "cells", {}):
            out.setdefault(ident, []).append(Finding(1, "missing-cell", f"exercise {ident.replace('-', '.')}"))
        if "check" not in getattr(mine.get(ident), "cells", {}):  # where its check runs is unknown: all of them
            out.setdefault(ident, []).extend(f for origin, f in carried if origin != ident)
    return {ident: _unique(out[ident]) for ident in reference if out.get(ident)}


def _answer_findings(ref: exercises.Exercise, answer: str, context: dict) -> list[Finding]:
    """An answer cell's findings, read against the exercise's solution and check."""
    solution = "\n".join(ln for ln in ref.answer.splitlines() if ln.strip() not in exercises.SOLUTION_MARKERS)
    return review_cell(answer, computed=computed_names(solution, ref.check), given=given_inputs(ref.answer, ref.check),
                       **context)


def _unique(found: list[Finding]) -> list[Finding]:
    return list({f: None for f in found})
