"""The Jupyter server extension that opens the git-tracked lesson notebooks read-only: JupyterLab
never autosaves them, a save to them is refused, every other file stays writable; and the install
enables it in the environment."""

import asyncio
import json
import shutil
import subprocess
from pathlib import Path

import nbformat
import pytest

from geodepth_lite import lesson_guard

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(shutil.which("git") is None, reason="git is not installed")


def git(cwd, *args):
    subprocess.run(["git", "-C", str(cwd), *args], check=True, capture_output=True)


def checkout(tmp_path, marker=True, solutions=True):
    """A git work tree shaped like a geodepth-lite checkout: notebooks/lesson.ipynb tracked (with a
    solution region unless ``solutions`` is False: a student edition), notebooks/mine.ipynb not."""
    repo = tmp_path / "repo"
    (repo / "notebooks").mkdir(parents=True)
    if marker:
        (repo / "geodepth_lite").mkdir()
        (repo / "geodepth_lite" / "lesson_guard.py").write_text("")
    solved = "x = None\n### BEGIN SOLUTION\nx = 1\n### END SOLUTION" if solutions else "x = None"
    for name in ("lesson", "mine"):
        nb = nbformat.v4.new_notebook(cells=[nbformat.v4.new_markdown_cell("### BEGIN SOLUTION is a marker"),
                                             nbformat.v4.new_code_cell(solved if name == "lesson" else "")])
        nbformat.write(nb, repo / "notebooks" / f"{name}.ipynb")
    git(repo, "init", "-q")
    git(repo, "add", "notebooks/lesson.ipynb", *(["geodepth_lite"] if marker else []))
    return repo


def manager(root, cls_name="AsyncLargeFileManager"):
    from jupyter_server.services.contents import largefilemanager

    cm = getattr(largefilemanager, cls_name)(root_dir=str(root))
    lesson_guard.guard(cm)
    return cm


def call(result):
    return asyncio.run(result) if asyncio.iscoroutine(result) else result


@pytest.mark.parametrize("cls_name", ["AsyncLargeFileManager", "LargeFileManager"])
def test_tracked_lessons_are_not_writable_and_cannot_be_saved(tmp_path, cls_name):
    from tornado.web import HTTPError

    cm = manager(checkout(tmp_path), cls_name)
    lesson = call(cm.get("notebooks/lesson.ipynb"))
    assert lesson["writable"] is False and lesson["type"] == "notebook"
    assert call(cm.get("notebooks/mine.ipynb"))["writable"] is True  # the student's own copy
    listing = {m["name"]: m["writable"] for m in call(cm.get("notebooks"))["content"]}
    assert listing == {"lesson.ipynb": False, "mine.ipynb": True}
    with pytest.raises(HTTPError, match="Save Notebook As") as refused:
        call(cm.save(lesson, "notebooks/lesson.ipynb"))
    assert refused.value.status_code == 403
    saved = call(cm.save(lesson, "notebooks/copy.ipynb"))  # "save as" a new name works, and stays writable
    assert saved["writable"] is True and (cm.root_dir and Path(cm.root_dir, "notebooks", "copy.ipynb").is_file())


def test_a_newly_tracked_notebook_is_guarded_and_other_repositories_are_not(tmp_path):
    repo = checkout(tmp_path)
    cm = manager(repo)
    assert call(cm.get("notebooks/mine.ipynb"))["writable"] is True
    git(repo, "add", "notebooks/mine.ipynb")  # the git index changed: read again
    assert call(cm.get("notebooks/mine.ipynb"))["writable"] is False
    edition = manager(checkout(tmp_path / "edition", solutions=False))  # students fill these in: writable
    assert call(edition.get("notebooks/lesson.ipynb"))["writable"] is True
    other = manager(checkout(tmp_path / "other", marker=False))  # a git repository that is not a geodepth-lite checkout
    assert call(other.get("notebooks/lesson.ipynb"))["writable"] is True
    outside = tmp_path / "plain"
    outside.mkdir()
    nbformat.write(nbformat.v4.new_notebook(), outside / "n.ipynb")
    assert call(manager(outside).get("n.ipynb"))["writable"] is True


def test_the_extension_can_be_turned_off_for_authors(tmp_path, monkeypatch):
    class App:
        class log:
            info = staticmethod(lambda *a: None)

    from jupyter_server.services.contents.largefilemanager import AsyncLargeFileManager

    App.contents_manager = AsyncLargeFileManager(root_dir=str(checkout(tmp_path)))
    monkeypatch.setenv(lesson_guard.EDIT_ENV, "1")
    lesson_guard._load_jupyter_server_extension(App)
    assert call(App.contents_manager.get("notebooks/lesson.ipynb"))["writable"] is True
    monkeypatch.delenv(lesson_guard.EDIT_ENV)
    lesson_guard._load_jupyter_server_extension(App)
    assert call(App.contents_manager.get("notebooks/lesson.ipynb"))["writable"] is False


def test_the_install_enables_the_extension():
    """environment.txt installs jupyter-config/ (not editable: an editable install drops data files),
    which puts the config file that enables the extension into <environment>/etc/jupyter."""
    lines = [ln.strip() for ln in (ROOT / "environment.txt").read_text().splitlines()]
    assert "./jupyter-config" in lines and lines.index("./jupyter-config") > lines.index("-e .")
    meta = (ROOT / "jupyter-config" / "pyproject.toml").read_text()
    assert '"etc/jupyter/jupyter_server_config.d" = ["jupyter_server_config.d/geodepth_lite.json"]' in meta
    config = json.loads((ROOT / "jupyter-config" / "jupyter_server_config.d" / "geodepth_lite.json").read_text())
    assert config == {"ServerApp": {"jpserver_extensions": {"geodepth_lite.lesson_guard": True}}}
    assert lesson_guard._jupyter_server_extension_points() == [{"module": "geodepth_lite.lesson_guard"}]
    assert (ROOT / Path(*lesson_guard.PACKAGE_MARKER)).is_file()  # this checkout is recognised as one
