"""A Jupyter server extension: the lesson notebooks of a geodepth-lite checkout open read-only.

Running a notebook changes its outputs, and JupyterLab saves a changed notebook every two minutes
on its own. Without this extension, opening ``notebooks/03_losses_explained.ipynb`` and pressing
Run All rewrites the committed file even if the student never saves. With it, the Jupyter server
reports every notebook that git tracks under ``notebooks/`` of a geodepth-lite checkout as not
writable (``"writable": false`` in the contents model): JupyterLab then never autosaves it, and
File > Save Notebook As... keeps the student's work in a copy of their own (an untracked file,
writable as usual). Every verb of the contents API that would change a lesson is refused with a
message that says so (HTTP 403): a save (PUT, also in chunks), a delete (DELETE), a rename away
or onto its name (PATCH), a copy onto its name, and the restore of a checkpoint over it (POST
``.../checkpoints/<id>``); so is a delete or rename of a folder that holds a lesson. The guard sits
in the contents manager's own methods (``save``, ``delete_file``, ``rename_file``,
``restore_checkpoint``), which every route of the API and every other caller goes through.

A student edition (``course edition``: the released notebooks, without solutions, that students
fill in and hand back under the same name) is left alone even when it is kept in git: the guard
applies only to a checkout where some tracked lesson notebook holds a solution region.

The editable install enables it for every Jupyter server of that environment through
``etc/jupyter/jupyter_server_config.d/geodepth_lite.json``. ``GEODEPTH_LITE_EDIT_LESSONS=1``
in the server's environment turns it off (for authors who edit the lessons in JupyterLab).
Only the standard library and tornado here: the server imports this module at start-up.
"""

from __future__ import annotations

import inspect
import json
import os
import stat
import subprocess
from pathlib import Path

from tornado.web import HTTPError  # the Jupyter server's own web framework: present wherever this runs

LESSON_DIR = "notebooks"  # lesson notebooks sit here in a checkout
# what makes a git work tree a geodepth-lite checkout
PACKAGE_MARKER = ("geodepth_lite", "workbook", "lesson_guard.py")
EDIT_ENV = "GEODEPTH_LITE_EDIT_LESSONS"  # "1": lessons stay writable (authors)
SOLUTION_MARKER = "### BEGIN SOLUTION"  # nbgrader's; a line of a code cell in the solved lessons only
MAX_NOTEBOOK_BYTES = 256 * 2**20  # larger files are not read for the marker
REFUSED = ("cannot {verb} {path}: {what} a lesson notebook of this checkout (tracked by git), which opens "
           "read-only so that running it never rewrites the lesson: keep your work with File > Save Notebook As... "
           "under another name")
SKIP_DIRS = ("node_modules", "__pycache__")  # never searched for checkouts (nor are hidden folders)


class TrackedLessons:
    """Which files are git-tracked lesson notebooks (``notebooks/*.ipynb``) of a geodepth-lite checkout.

    ``git ls-files`` runs once per checkout and again only when its git index changes, so a
    directory listing asks git nothing per file.
    """

    def __init__(self):
        self._tops: dict[Path, Path | None] = {}  # folder -> its checkout's top (None: not in one)
        self._tracked: dict[Path, tuple[tuple, frozenset]] = {}  # top -> (index stamp, tracked lesson paths)

    def _top(self, folder: Path) -> Path | None:
        if folder not in self._tops:
            top = None
            for d in (folder, *folder.parents):
                if (d / ".git").exists():
                    top = d if d.joinpath(*PACKAGE_MARKER).is_file() else None
                    break
            self._tops[folder] = top
        return self._tops[folder]

    def _lessons(self, top: Path) -> frozenset:
        index = top / ".git" / "index"  # a clone's index; a linked work tree (.git is a file) re-reads each time
        stamp = (index.stat().st_mtime_ns, index.stat().st_size) if index.is_file() else None
        cached = self._tracked.get(top)
        if cached is not None and stamp is not None and cached[0] == stamp:
            return cached[1]
        try:
            out = subprocess.run(["git", "-C", str(top), "ls-files", "-z", "--", f"{LESSON_DIR}/*.ipynb"],
                                 capture_output=True, timeout=20, check=True).stdout
        except (OSError, subprocess.SubprocessError):  # no git: nothing is known to be tracked
            return frozenset()
        lessons = frozenset(os.fsdecode(p) for p in out.split(b"\0") if p)
        if not any(_holds_solutions(top / rel) for rel in lessons):
            lessons = frozenset()  # a student edition: its notebooks are the students' own work
        self._tracked[top] = (stamp, lessons)
        return lessons

    def is_lesson(self, file: str | os.PathLike) -> bool:
        """True if ``file`` is a lesson notebook that git tracks in a geodepth-lite checkout."""
        file = Path(os.path.realpath(file))
        if file.suffix != ".ipynb":
            return False
        top = self._top(file.parent)
        if top is None:
            return False
        rel = file.relative_to(top).as_posix()
        return rel.startswith(LESSON_DIR + "/") and rel in self._lessons(top)

    def holds_lesson(self, folder: str | os.PathLike) -> bool:
        """True if the folder ``folder`` holds a lesson notebook (at any depth): a checkout's
        ``notebooks/``, the checkout itself, or a folder above one or more checkouts."""
        folder = Path(os.path.realpath(folder))
        if not folder.is_dir():
            return False
        top = self._top(folder)
        if top is not None:
            return any(folder in (top / rel).parents for rel in self._lessons(top))
        for here, dirs, _ in os.walk(folder):  # above any checkout: find the checkouts below
            here = Path(here)
            if (here / ".git").exists():
                if self._top(here) == here and self._lessons(here):
                    return True
            dirs[:] = [d for d in dirs if not d.startswith(".") and d not in SKIP_DIRS]
        return False


def _holds_solutions(path: Path) -> bool:
    """Whether the notebook ``path`` has a code cell with a :data:`SOLUTION_MARKER` line."""
    try:
        st = path.stat()
        if not stat.S_ISREG(st.st_mode) or st.st_size > MAX_NOTEBOOK_BYTES:
            return False  # a FIFO in a lesson's place would block the first read, and the server with it
        cells = json.loads(path.read_bytes()).get("cells", [])
    except (OSError, ValueError, AttributeError):
        return False
    for cell in cells if isinstance(cells, list) else ():
        source = cell.get("source", "") if isinstance(cell, dict) else ""
        text = "".join(source) if isinstance(source, list) else str(source)
        if cell.get("cell_type") == "code" and any(ln.strip() == SOLUTION_MARKER for ln in text.splitlines()):
            return True
    return False


def _refusal(lessons: TrackedLessons, root: str, verb: str, *paths: str) -> HTTPError | None:
    """The HTTP 403 for ``verb`` on API ``paths`` where one is, or holds, a lesson notebook; else None."""
    for path in paths:
        file = os.path.join(root, path.strip("/"))
        what = "it is" if lessons.is_lesson(file) else "it holds" if lessons.holds_lesson(file) else ""
        if what:
            return HTTPError(403, REFUSED.format(verb=verb, path=path.strip("/"), what=what))
    return None


def guard(contents_manager, lessons: TrackedLessons | None = None) -> None:
    """Make ``contents_manager`` (a Jupyter server's, sync or async) report lesson notebooks as not
    writable, in their own models and in directory listings, and refuse every change to them: save,
    delete, rename (away or onto), copy onto, checkpoint restore."""
    lessons = lessons or TrackedLessons()
    cm = contents_manager
    checks = {  # method -> (verb, which arguments are API paths that must not be, or hold, a lesson)
        "save": ("save", lambda model, path, *a, **k: [path]),
        "delete_file": ("delete", lambda path, *a, **k: [path]),
        "rename_file": ("rename", lambda old_path, new_path, *a, **k: [old_path, new_path]),
        "restore_checkpoint": ("restore a checkpoint over", lambda checkpoint_id, path, *a, **k: [path]),
    }

    def mark(model: dict) -> dict:
        if model.get("type") == "notebook" and lessons.is_lesson(os.path.join(cm.root_dir, model["path"])):
            model["writable"] = False
        for child in model.get("content") or () if model.get("type") == "directory" else ():
            mark(child)
        return model

    def wrap(method, verb, paths):
        if inspect.iscoroutinefunction(method):
            async def guarded(*args, **kwargs):
                refused = _refusal(lessons, cm.root_dir, verb, *paths(*args, **kwargs))
                if refused is not None:
                    raise refused
                return await method(*args, **kwargs)
        else:
            def guarded(*args, **kwargs):
                refused = _refusal(lessons, cm.root_dir, verb, *paths(*args, **kwargs))
                if refused is not None:
                    raise refused
                return method(*args, **kwargs)
        return guarded

    get = cm.get
    if inspect.iscoroutinefunction(get):
        async def guarded_get(path, *args, **kwargs):
            return mark(await get(path, *args, **kwargs))
    else:
        def guarded_get(path, *args, **kwargs):
            return mark(get(path, *args, **kwargs))
    cm.get = guarded_get
    for name, (verb, paths) in checks.items():
        setattr(cm, name, wrap(getattr(cm, name), verb, paths))


def _jupyter_server_extension_points():
    return [{"module": "geodepth_lite.workbook.lesson_guard"}]


def _load_jupyter_server_extension(serverapp):
    if os.environ.get(EDIT_ENV) == "1":
        serverapp.log.info("geodepth-lite: lesson notebooks stay writable (%s=1)", EDIT_ENV)
        return
    guard(serverapp.contents_manager)
    serverapp.log.info("geodepth-lite: git-tracked lesson notebooks open read-only (save a copy to keep your work)")
