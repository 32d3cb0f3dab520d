"""The Jupyter server extension that opens the git-tracked lesson notebooks read-only: JupyterLab
never autosaves them; a save, delete, rename (away or onto), copy onto or checkpoint restore is
refused, in the contents manager and through the HTTP API of a real Jupyter server on 127.0.0.1;
every other file stays writable (Save As works); and the install enables it in the environment."""

import asyncio
import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import nbformat
import pytest

from geodepth_lite.workbook import lesson_guard

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
        (repo / "geodepth_lite" / "workbook").mkdir(parents=True)
        (repo / "geodepth_lite" / "workbook" / "lesson_guard.py").write_text("")
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
    assert config == {"ServerApp": {"jpserver_extensions": {"geodepth_lite.workbook.lesson_guard": True}}}
    assert lesson_guard._jupyter_server_extension_points() == [{"module": "geodepth_lite.workbook.lesson_guard"}]
    assert (ROOT / Path(*lesson_guard.PACKAGE_MARKER)).is_file()  # this checkout is recognised as one


@pytest.mark.parametrize("cls_name", ["AsyncLargeFileManager", "LargeFileManager"])
def test_every_verb_that_would_change_a_lesson_is_refused(tmp_path, cls_name):
    """delete, rename away, rename onto, copy onto, a folder that holds it, checkpoint restore: 403 each,
    the lesson byte-identical; the same verbs on the student's own notebook work."""
    from tornado.web import HTTPError

    repo = checkout(tmp_path)
    lesson = repo / "notebooks" / "lesson.ipynb"
    before = lesson.read_bytes()
    cm = manager(repo, cls_name)
    cm.delete_to_trash = False
    checkpoint = call(cm.create_checkpoint("notebooks/lesson.ipynb"))  # a copy of it: allowed
    cp_file = repo / "notebooks" / ".ipynb_checkpoints" / "lesson-checkpoint.ipynb"
    cp_file.write_bytes(before.replace(b"x = 1", b"x = 2"))  # a checkpoint that differs from the lesson
    refused = [lambda: cm.delete("notebooks/lesson.ipynb"),
               lambda: cm.rename("notebooks/lesson.ipynb", "notebooks/away.ipynb"),
               lambda: cm.update({"path": "notebooks/away.ipynb"}, "notebooks/lesson.ipynb"),
               lambda: cm.rename("notebooks/mine.ipynb", "notebooks/lesson.ipynb"),
               lambda: cm.rename("notebooks/mine.ipynb", "notebooks/../notebooks/lesson.ipynb"),
               lambda: cm.copy("notebooks/mine.ipynb", "notebooks/lesson.ipynb"),
               lambda: cm.delete("notebooks"),
               lambda: cm.rename("notebooks", "lessons"),
               lambda: cm.restore_checkpoint(checkpoint["id"], "notebooks/lesson.ipynb")]
    for k, attempt in enumerate(refused):
        with pytest.raises(HTTPError) as caught:
            call(attempt())
        assert caught.value.status_code == 403 and "lesson notebook" in caught.value.log_message, k
        assert lesson.read_bytes() == before, k
    whole = manager(tmp_path, cls_name)  # served from above the checkout: the checkout itself holds lessons
    with pytest.raises(HTTPError, match="it holds a lesson"):
        call(whole.delete("repo"))
    # the student's own notebook: every verb works
    call(cm.copy("notebooks/lesson.ipynb", "notebooks"))  # "lesson-Copy1.ipynb"
    call(cm.rename("notebooks/mine.ipynb", "notebooks/mine2.ipynb"))
    call(cm.delete("notebooks/mine2.ipynb"))
    assert sorted(p.name for p in (repo / "notebooks").glob("*.ipynb")) == ["lesson-Copy1.ipynb", "lesson.ipynb"]


def test_the_guard_fails_when_a_verb_is_left_unguarded(tmp_path):
    """The check above catches a guard that misses a verb: without the rename_file hook, a rename away works."""
    repo = checkout(tmp_path)
    from jupyter_server.services.contents.largefilemanager import LargeFileManager

    cm = LargeFileManager(root_dir=str(repo))
    rename_file = cm.rename_file
    lesson_guard.guard(cm)
    cm.rename_file = rename_file  # the planted defect
    cm.rename("notebooks/lesson.ipynb", "notebooks/away.ipynb")
    assert not (repo / "notebooks" / "lesson.ipynb").exists()


def test_a_fifo_in_a_lessons_place_does_not_hang_the_server(tmp_path):
    """A FIFO where a tracked lesson was (made by hand in the work tree) is not read: the guard's check for
    solutions answers at once, instead of blocking the Jupyter server on its first read."""
    repo = checkout(tmp_path)
    (repo / "notebooks" / "lesson.ipynb").unlink()
    os.mkfifo(repo / "notebooks" / "lesson.ipynb")

    def hung(*_):
        raise AssertionError("the guard blocked on the FIFO")

    previous = signal.signal(signal.SIGALRM, hung)
    signal.alarm(10)
    try:
        assert lesson_guard._holds_solutions(repo / "notebooks" / "lesson.ipynb") is False
        assert lesson_guard.TrackedLessons().is_lesson(repo / "notebooks" / "lesson.ipynb") is False
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


# --------------------------------------------------------------------------- a real Jupyter server


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """``jupyter server`` on 127.0.0.1 serving a crafted checkout, with the environment's own extensions
    and this one enabled; yields (request function, checkout)."""
    pytest.importorskip("jupyter_server")
    tmp = tmp_path_factory.mktemp("jupyter")
    repo = checkout(tmp)
    port, token = _free_port(), secrets.token_hex(16)
    env = {**os.environ, "JUPYTER_CONFIG_DIR": str(tmp / "cfg"), "JUPYTER_DATA_DIR": str(tmp / "data"),
           "JUPYTER_RUNTIME_DIR": str(tmp / "run"), "HOME": str(tmp), "PYTHONPATH": str(ROOT)}
    env.pop(lesson_guard.EDIT_ENV, None)
    log = open(tmp / "server.log", "wb")
    args = ["--no-browser", "--allow-root", "--ServerApp.ip=127.0.0.1", f"--ServerApp.port={port}",
            "--ServerApp.port_retries=0", f"--ServerApp.root_dir={repo}", f"--IdentityProvider.token={token}",
            "--FileContentsManager.delete_to_trash=False", "--ServerApp.jpserver_extensions",
            "geodepth_lite.workbook.lesson_guard=True"]
    proc = subprocess.Popen([sys.executable, "-m", "jupyter_server", *args], env=env, cwd=repo, stdout=log,
                            stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    base = f"http://127.0.0.1:{port}/api/contents/"

    def request(method, path, body=None):
        data = None if body is None else json.dumps(body).encode()
        req = urllib.request.Request(base + path, data=data, method=method,
                                     headers={"Authorization": f"token {token}", "Content-Type": "application/json"})
        try:
            with urllib.request.urlopen(req, timeout=60) as resp:
                return resp.status, json.loads(resp.read() or b"null")
        except urllib.error.HTTPError as exc:
            return exc.code, json.loads(exc.read() or b"null")

    deadline = time.monotonic() + 120
    while True:
        try:
            if request("GET", "")[0] == 200:
                break
        except OSError:
            pass
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            pytest.fail("jupyter server did not start: " + (tmp / "server.log").read_text()[-2000:])
        time.sleep(0.5)
    yield request, repo
    proc.terminate()
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
    log.close()


def test_a_real_server_refuses_every_verb_and_sequence(server):
    """Through the contents API of a running Jupyter server: each verb and each sequence that replaced or
    removed a lesson leaves it byte-identical; Save As and the same verbs on other notebooks work."""
    request, repo = server
    lesson = repo / "notebooks" / "lesson.ipynb"
    before = lesson.read_bytes()
    status, model = request("GET", "notebooks/lesson.ipynb")
    assert status == 200 and model["writable"] is False
    other = json.loads(before.replace(b"x = 1", b"x = 666"))

    def refused(method, path, body=None):
        status, answer = request(method, path, body)
        assert status == 403 and "lesson notebook" in answer["message"], (method, path, status, answer)
        assert lesson.read_bytes() == before, (method, path)

    refused("DELETE", "notebooks/lesson.ipynb")
    refused("PATCH", "notebooks/lesson.ipynb", {"path": "notebooks/away.ipynb"})  # rename away
    refused("PUT", "notebooks/lesson.ipynb", {"type": "notebook", "format": "json", "content": other})
    refused("PUT", "notebooks/lesson.ipynb", {"type": "file", "format": "text", "content": "{}", "chunk": 1})
    refused("DELETE", "notebooks")  # the folder that holds it
    refused("PATCH", "notebooks", {"path": "lessons"})
    # Save As: a copy under another name is the student's, and every verb works on it
    assert request("PUT", "notebooks/copy.ipynb", {"type": "notebook", "format": "json", "content": other})[0] == 201
    assert request("GET", "notebooks/copy.ipynb")[1]["writable"] is True
    assert request("PUT", "notebooks/copy.ipynb", {"type": "notebook", "format": "json", "content": other})[0] == 200
    # rename another notebook onto the lesson's name (after a delete, or over it): refused
    refused("PATCH", "notebooks/copy.ipynb", {"path": "notebooks/lesson.ipynb"})
    refused("PATCH", "notebooks/copy.ipynb", {"path": "notebooks/sub/../lesson.ipynb"})
    status, copied = request("POST", "notebooks", {"copy_from": "notebooks/lesson.ipynb"})  # a copy of it: allowed
    assert status == 201 and copied["path"] == "notebooks/lesson-Copy1.ipynb"
    # a checkpoint of the lesson may be made; restoring one over it is refused
    status, checkpoint = request("POST", "notebooks/lesson.ipynb/checkpoints")
    assert status == 201
    (repo / "notebooks" / ".ipynb_checkpoints" / "lesson-checkpoint.ipynb").write_text(json.dumps(other))
    refused("POST", f"notebooks/lesson.ipynb/checkpoints/{checkpoint['id']}")
    # the lesson gone from the work tree (deleted outside Jupyter): nothing may take its name
    lesson.unlink()
    for attempt in (("PATCH", "notebooks/copy.ipynb", {"path": "notebooks/lesson.ipynb"}),
                    ("PUT", "notebooks/lesson.ipynb", {"type": "notebook", "format": "json", "content": other})):
        status, _ = request(*attempt)
        assert status == 403 and not lesson.exists(), attempt
    lesson.write_bytes(before)
    assert request("PATCH", "notebooks/copy.ipynb", {"path": "notebooks/copy2.ipynb"})[0] == 200
    assert request("DELETE", "notebooks/copy2.ipynb")[0] == 204
    assert lesson.read_bytes() == before
