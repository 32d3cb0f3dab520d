"""A Jupyter server extension: the lesson notebooks of a geodepth-lite checkout open read-only.

Running a notebook changes its outputs, and JupyterLab saves a changed notebook every two minutes
on its own. Without this extension, opening ``notebooks/03_losses_explained.ipynb`` and pressing
Run All rewrites the committed file even if the student never saves. With it, the Jupyter server
reports every notebook that git tracks under ``notebooks/`` of a geodepth-lite checkout as not
writable (``"writable": false`` in the contents model): JupyterLab then never autosaves it, and
File > Save Notebook As... keeps the student's work in a copy of their own (an untracked file,
writable as usual). A save to a lesson notebook is refused with a message that says so.

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
import subprocess
from pathlib import Path

from tornado.web import HTTPError  # the Jupyter server's own web framework: present wherever this runs

LESSON_DIR = "notebooks"  # lesson notebooks sit here in a checkout
PACKAGE_MARKER = ("geodepth_lite", "lesson_guard.py")  # what makes a git work tree a geodepth-lite checkout
EDIT_ENV = "GEODEPTH_LITE_EDIT_LESSONS"  # "1": lessons stay writable (authors)
SOLUTION_MARKER = "### BEGIN SOLUTION"  # nbgrader's; a line of a code cell in the solved lessons only
MAX_NOTEBOOK_BYTES = 256 * 2**20  # larger files are not read for the marker
SAVE_REFUSED = ("{path} is a lesson notebook of this checkout (tracked by git) and opens read-only, so that running "
                "it never rewrites the lesson: keep your work with File > Save Notebook As... under another name")


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


def _holds_solutions(path: Path) -> bool:
    """Whether the notebook ``path`` has a code cell with a :data:`SOLUTION_MARKER` line."""
    try:
        if path.stat().st_size > MAX_NOTEBOOK_BYTES:
            return False
        cells = json.loads(path.read_bytes()).get("cells", [])
    except (OSError, ValueError, AttributeError):
        return False
    for cell in cells if isinstance(cells, list) else ():
        source = cell.get("source", "") if isinstance(cell, dict) else ""
        text = "".join(source) if isinstance(source, list) else str(source)
        if cell.get("cell_type") == "code" and any(ln.strip() == SOLUTION_MARKER for ln in text.splitlines()):
            return True
    return False


def guard(contents_manager, lessons: TrackedLessons | None = None) -> None:
    """Make ``contents_manager`` (a Jupyter server's, sync or async) report lesson notebooks as not
    writable, in their own models and in directory listings, and refuse to save them."""
    lessons = lessons or TrackedLessons()
    get, save = contents_manager.get, contents_manager.save

    def is_lesson(path: str) -> bool:
        return lessons.is_lesson(os.path.join(contents_manager.root_dir, path.strip("/")))

    def mark(model: dict) -> dict:
        if model.get("type") == "notebook" and is_lesson(model["path"]):
            model["writable"] = False
        for child in model.get("content") or () if model.get("type") == "directory" else ():
            mark(child)
        return model

    def refuse(path: str) -> None:
        if is_lesson(path):
            raise HTTPError(403, SAVE_REFUSED.format(path=path.strip("/")))

    if inspect.iscoroutinefunction(get):
        async def guarded_get(path, *args, **kwargs):
            return mark(await get(path, *args, **kwargs))

        async def guarded_save(model, path, *args, **kwargs):
            refuse(path)
            return await save(model, path, *args, **kwargs)
    else:
        def guarded_get(path, *args, **kwargs):
            return mark(get(path, *args, **kwargs))

        def guarded_save(model, path, *args, **kwargs):
            refuse(path)
            return save(model, path, *args, **kwargs)

    contents_manager.get, contents_manager.save = guarded_get, guarded_save


def _jupyter_server_extension_points():
    return [{"module": "geodepth_lite.lesson_guard"}]


def _load_jupyter_server_extension(serverapp):
    if os.environ.get(EDIT_ENV) == "1":
        serverapp.log.info("geodepth-lite: lesson notebooks stay writable (%s=1)", EDIT_ENV)
        return
    guard(serverapp.contents_manager)
    serverapp.log.info("geodepth-lite: git-tracked lesson notebooks open read-only (save a copy to keep your work)")
