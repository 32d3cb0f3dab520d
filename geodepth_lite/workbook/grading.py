"""Checks that test the skill: hidden tests forbid the package functions an exercise asks the student
to write, so that calling them instead loses the points.

An exercise of notebooks 01-07 often asks for something the package already has (Holm's rule, the
seven metrics, the smoothness loss...), and its check compares the student's answer with that very
function. Calling it would pass. The hidden tests therefore run the student's code under
:func:`forbid`::

    from geodepth_lite.evaluation import ablation
    from geodepth_lite.workbook import grading

    _want = ablation.holm(_p)                       # the reference first, while it is allowed
    with grading.forbid(ablation.holm, task="write holm yourself", namespace=globals()):
        assert holm(_p) == _want                    # a holm() that calls ablation.holm raises here
        grading.rerun_answer(globals(), ["holm"])   # and so does an answer cell that does

While the block runs, each forbidden function raises :class:`ForbiddenCall` (an AssertionError, so
nbgrader counts it as a failed test) saying "this exercise asks you to write holm yourself; calling
geodepth_lite.evaluation.ablation.holm is not allowed". It is replaced in its own module, in every loaded
``geodepth_lite`` module that imported it, and under any name of ``namespace`` (the notebook's
``globals()``) bound to it; a class has its own methods replaced, so a network built before the block
cannot run either; a module stands for all the functions and classes it defines. A reference taken
earlier (a default argument, a closure) still reaches the function's code, which a profile hook
catches. Everything is put back when the block ends.

An answer *value* computed in the answer cell (``my_report = integrity.verify(root)``) was computed
before the check ran: :func:`rerun_answer` runs the answer cell again, under the block, from the
kernel's input history (``In``; :func:`geodepth_lite.workbook.exercises.run_exercise` keeps one too). A kernel that
records no history (nbval runs cells with ``store_history=False``) has nothing to run again: the notebook
tests check the committed solutions, nbgrader's autograde records the history.

Answers are checked for their exact types where the checks see them through this module: an answer of a
subclass can redefine ``==`` (a set equal to any set). :func:`rerun_answer` refuses answer variables not
built of plain values (:func:`foreign_value`: ``type(x) is set``, ``int``, ``str``, numpy's scalars and
arrays, ``torch.Tensor``, and lists, tuples, dicts and sets of them), and inside :func:`forbid` every
function the answer cell defines (the cell before the check, from the input history) must return such values.
"""

from __future__ import annotations

import ast
import collections
import contextlib
import functools
import inspect
import io
import sys
import types
from typing import Any, Iterable, Iterator

import numpy as np

PACKAGE = "geodepth_lite"
SCALARS = frozenset({type(None), bool, int, float, complex, str, bytes, *np.sctypeDict.values()})
CONTAINERS = (list, tuple, dict, set, frozenset, collections.OrderedDict, collections.defaultdict, collections.Counter)
ITEMS_CHECKED = 100_000  # elements of an answer looked at before the rest is taken on trust


class ForbiddenCall(AssertionError):
    """A forbidden function was called while a check ran."""


def _qualified(obj) -> str:
    module = getattr(obj, "__module__", None) or "?"
    return f"{module}.{getattr(obj, '__qualname__', None) or getattr(obj, '__name__', repr(obj))}"


def _raiser(message: str, name: str):
    def forbidden(*args, **kwargs):
        raise ForbiddenCall(message)

    forbidden.__name__ = forbidden.__qualname__ = name
    forbidden.__doc__ = message
    return forbidden


def _owner_of(fn) -> tuple[Any, str] | None:
    """(module or class, attribute name) where a function or class is defined, if it can be found."""
    module = sys.modules.get(getattr(fn, "__module__", None) or "")
    qualname = getattr(fn, "__qualname__", None) or getattr(fn, "__name__", None)
    if module is None or not qualname or "<locals>" in qualname:
        return None
    owner: Any = module
    *path, name = qualname.split(".")
    for part in path:
        owner = getattr(owner, part, None)
        if owner is None:
            return None
    return (owner, name) if getattr(owner, name, None) is fn else None


def _code_of(fn):
    """The code object that runs when ``fn`` is called, to watch: that of the function a decorator wraps
    (``functools.wraps`` records it as ``__wrapped__``), never the decorator's wrapper, whose code every
    function with that decorator shares (``@torch.no_grad()`` of a student's own function among them);
    None where only a shared wrapper's code is found (its name differs from the function's)."""
    fn = inspect.unwrap(getattr(fn, "__func__", fn))
    code = getattr(fn, "__code__", None)
    if code is not None and code.co_name != getattr(fn, "__name__", code.co_name):
        return None
    return code


def _expand(targets) -> list[tuple[Any, str, Any]]:
    """(owner, attribute, object) for each function to forbid."""
    out = []
    for target in targets:
        if isinstance(target, tuple):
            owner, name = target
            out.append((owner, name, getattr(owner, name)))
        elif isinstance(target, types.ModuleType):
            for name, obj in list(vars(target).items()):
                if callable(obj) and getattr(obj, "__module__", None) == target.__name__ and not name.startswith("__"):
                    out.extend(_expand([obj]) if isinstance(obj, type) else [(target, name, obj)])
        elif isinstance(target, type):
            for name, obj in list(vars(target).items()):
                if isinstance(obj, (types.FunctionType, staticmethod, classmethod)):
                    out.append((target, name, getattr(target, name)))
            if "__init__" not in vars(target):  # building one is forbidden too
                out.append((target, "__init__", target.__init__))
        elif callable(target):
            where = _owner_of(target)
            if where is None:
                raise ValueError(f"cannot forbid {target!r}: its module or class is not found; pass (owner, name)")
            out.append((where[0], where[1], target))
        else:
            raise TypeError(f"cannot forbid {target!r}: not a function, class, module or (owner, name) pair")
    return out


def _profile_guard(codes: dict, builtins: dict, previous):
    """A profile function raising ForbiddenCall when a forbidden function's code starts (a reference
    taken before the block, e.g. a default argument) or a forbidden builtin is called."""

    def guard(frame, event, arg):
        if event == "call" and frame.f_code in codes:
            raise ForbiddenCall(codes[frame.f_code])
        if event == "c_call" and id(arg) in builtins and builtins[id(arg)][0] is arg:
            raise ForbiddenCall(builtins[id(arg)][1])
        if previous is not None:
            previous(frame, event, arg)

    return guard


def _answer_functions(namespace: dict) -> set[str]:
    """The names of the functions the answer cell defines (``def`` at its top level); none where the kernel
    records no input history (nbval's runs of the committed notebooks) or the cell cannot be read."""
    try:
        source = answer_source(namespace)
        tree = ast.parse(source) if source is not None else None
    except (AssertionError, SyntaxError, ValueError):
        return set()
    defined = (ast.FunctionDef, ast.AsyncFunctionDef)
    return {node.name for node in getattr(tree, "body", []) if isinstance(node, defined)}


def _check_returns(namespace: dict) -> list[tuple[dict, str, Any, bool]]:
    """Each function the answer cell defined (its globals are ``namespace``; a decorated one too) replaced
    in ``namespace`` by one whose return value must be plain (:func:`foreign_value`); the patches, to undo."""
    patches = []
    for key in _answer_functions(namespace):
        value = namespace.get(key)
        if isinstance(value, types.FunctionType) and getattr(inspect.unwrap(value), "__globals__", None) is namespace:
            patches.append((namespace, key, value, True))
            namespace[key] = _returns_checked(value, key)
    return patches


@contextlib.contextmanager
def forbid(*targets, task: str, namespace: dict | None = None) -> Iterator[None]:
    """While the block runs, calling any of ``targets`` raises :class:`ForbiddenCall` (see the module
    docstring). ``targets``: functions, classes (their own methods, construction included), modules (every
    function and class they define) or (owner, attribute name) pairs; ``task``: what the exercise asks the
    student to do, for the message ("write holm yourself"); ``namespace``: the notebook's ``globals()``,
    whose names bound to a forbidden function are replaced too."""
    patches: list[tuple[Any, str, Any, bool]] = []  # (owner, name, original, owner had it in its own dict)
    codes: dict = {}
    builtins: dict = {}
    try:
        for owner, name, original in _expand(targets):
            label = _qualified(owner) if name == "__init__" and isinstance(owner, type) else None
            what = f"building {label}" if label else f"calling {_qualified(original)}"
            message = f"this exercise asks you to {task}; {what} is not allowed"
            replacement = _raiser(message, name)
            if isinstance(owner, type) and isinstance(vars(owner).get(name), staticmethod):
                replacement = staticmethod(replacement)
            patches.append((owner, name, vars(owner).get(name, None) if isinstance(owner, type) else original,
                            name in vars(owner)))
            setattr(owner, name, replacement)
            code = _code_of(original)
            if code is not None:
                codes[code] = message
            elif isinstance(original, types.BuiltinFunctionType):
                builtins[id(original)] = (original, message)
            aliases = [m for key, m in list(sys.modules.items()) if key == PACKAGE or key.startswith(PACKAGE + ".")]
            if not isinstance(owner, type):
                for module in aliases:
                    for key, value in list(vars(module).items()):
                        if value is original and not (module is owner and key == name):
                            patches.append((module, key, value, True))
                            setattr(module, key, replacement)
                if namespace is not None:
                    for key, value in list(namespace.items()):
                        if value is original:
                            patches.append((namespace, key, value, True))
                            namespace[key] = replacement
        if namespace is not None:
            patches += _check_returns(namespace)
        previous = sys.getprofile()
        sys.setprofile(_profile_guard(codes, builtins, previous))
        try:
            yield
        finally:
            sys.setprofile(previous)
    finally:
        for owner, name, original, had in reversed(patches):
            if isinstance(owner, dict):
                owner[name] = original
            elif had:
                setattr(owner, name, original)
            else:
                delattr(owner, name)


def _torch_types() -> tuple:
    """torch's exact value types, where torch is loaded (a value cannot be a tensor otherwise)."""
    torch = sys.modules.get("torch")
    return (torch.Tensor, torch.Size, torch.dtype, torch.device) if torch is not None else ()


def foreign_value(value, budget: list | None = None) -> str | None:
    """None when ``value`` is built of exact plain types only: None, bool, int, float, complex, str, bytes,
    numpy's scalars and arrays (not of dtype object), torch's tensors, and lists, tuples, dicts, sets of
    those; else what is not, e.g. "a value of type Always (a subclass of int)". A subclass can redefine
    ``==`` (a set equal to any set), so the checks compare types as well as values."""
    budget = [ITEMS_CHECKED] if budget is None else budget
    budget[0] -= 1
    if budget[0] < 0:
        return None
    kind = type(value)
    if kind in SCALARS or kind in _torch_types() or (kind is np.ndarray and value.dtype != object):
        return None
    if kind in CONTAINERS:
        items = [*value.keys(), *value.values()] if isinstance(value, dict) else value
        return next((why for why in (foreign_value(v, budget) for v in items) if why), None)
    bases = [b.__name__ for b in kind.__mro__[1:] if b in SCALARS or b in CONTAINERS or b in _torch_types()
             or b is np.ndarray]
    kin = f" (a subclass of {bases[0]})" if bases else ""
    return f"a value of type {kind.__name__}{kin}"


def check_plain(namespace: dict, names: Iterable[str]) -> None:
    """An AssertionError naming the first of ``names`` whose value in ``namespace`` is not built of plain
    types (:func:`foreign_value`); a function (what a function exercise defines) passes."""
    for name in names:
        value = namespace.get(name)
        if type(value) is types.FunctionType:
            continue
        why = foreign_value(value)
        if why:
            raise AssertionError(f"{name} holds {why}: answer with plain Python, numpy or torch values (the checks "
                                 "compare types as well as values)")


def _returns_checked(fn, name: str):
    """``fn`` whose return value must be plain (:func:`foreign_value`), else an AssertionError."""
    @functools.wraps(fn)
    def checked(*args, **kwargs):
        result = fn(*args, **kwargs)
        why = foreign_value(result)
        if why:
            raise AssertionError(f"{name}() returned {why}: return plain Python, numpy or torch values (the "
                                 "checks compare types as well as values)")
        return result

    return checked


def _shell():
    """The running IPython shell, or None outside a kernel."""
    try:
        from IPython import get_ipython  # optional: only a kernel has it, and the package imports without it
    except ImportError:  # pragma: no cover - IPython comes with Jupyter
        return None
    return get_ipython()


def answer_source(namespace: dict) -> str | None:
    """The source of the cell run before the current one (the exercise's answer cell when the check
    cell runs), from the kernel's input history (``exercises.run_exercise`` keeps one in ``In`` too).

    None where the kernel records no history at all (a cell run with ``store_history=False``, as the
    notebook tests' nbval does: the execution count never moves); an AssertionError where it records one
    but the answer cell is not in it."""
    shell = _shell()
    history = getattr(getattr(shell, "history_manager", None), "input_hist_parsed", None)
    if history is None:
        history = namespace.get("In") or namespace.get("_ih")
    if isinstance(history, list) and len(history) >= 2:
        return history[-2]
    if shell is not None and getattr(shell, "execution_count", 0) <= 1:
        return None
    raise AssertionError("cannot find the answer cell to run it again: run the notebook from the top")


def rerun_answer(namespace: dict, names: Iterable[str], source: str | None = None) -> dict:
    """Run the answer cell again (``source``, default :func:`answer_source`) in a copy of ``namespace``
    from which ``names`` (what the answer cell must set) are removed, its printing silenced; inside a
    :func:`forbid` block, an answer cell that calls a forbidden function fails. Returns the new
    namespace; an AssertionError when the cell does not set every one of ``names`` again. Where the
    kernel records no input history (``answer_source`` is None), nothing is run."""
    names = list(names)
    check_plain(namespace, names)
    source = answer_source(namespace) if source is None else source
    if source is None:  # no input history is recorded: nothing to run again
        return dict(namespace)
    fresh = {k: v for k, v in namespace.items() if k not in names}
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        exec(compile(source, "<answer, run again>", "exec"), fresh)  # noqa: S102 - the student's own cell
    missing = [n for n in names if n not in fresh]
    if missing:
        raise AssertionError(f"the answer cell, run again, does not set {', '.join(missing)}")
    check_plain(fresh, names)
    return fresh
