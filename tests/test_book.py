"""The web book (``python -m geodepth_lite book``): its pieces without a browser (folding the solutions,
links to the source, the output folder's refusals, the missing Node.js line, a failed build leaving
no site), then the real book built once and opened page by page in Debian's chromium through
Playwright: every page loads with no error, no image is missing, no markdown is left raw, the math
is typeset, and every solution stays folded until its control is clicked.

The browser test skips, saying why, where chromium, Playwright, Node.js or jupyter-book is missing;
with GEODEPTH_REQUIRE_BROWSER=1 it fails instead."""

import functools
import html
import http.server
import io
import json
import os
import re
import subprocess
import sys
import tarfile
import threading
from pathlib import Path
from types import SimpleNamespace

import pytest
from conftest import one_line_error

from geodepth_lite import cli
from geodepth_lite.workbook import book, exercises

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
REQUIRE_ENV = "GEODEPTH_REQUIRE_BROWSER"

# --------------------------------------------------------------------------- pieces, no browser


def test_split_folds_known_ranges():
    code = ("import torch\n\ndef f(x):\n    ### BEGIN SOLUTION\n    return x * 2\n    ### END SOLUTION\n"
            "assert f(1) == 2\n### BEGIN HIDDEN TESTS\nassert f(2) == 4\n### END HIDDEN TESTS")
    assert book.split_folds(code) == [("code", 0, 3), ("solution", 4, 5), ("code", 6, 7), ("hidden", 8, 9)]
    assert book.split_folds("x = 1\ny = 2") == [("code", 0, 2)]


def test_highlight_keeps_lines_and_links_package_names():
    modules = book.index_package()
    imports = "from geodepth_lite.core import losses as L\nfrom geodepth_lite.core.sdf import signed_distance"
    names = book.notebook_names([imports], modules)
    assert names.modules == {"L": "core.losses"}
    assert names.symbols == {"signed_distance": ("core.sdf", "signed_distance")}

    def link(chain):
        found = book.resolve(chain, names, modules)
        return found and (found[0], f"{found[1]}#{found[2]}")

    code = 'x = L.sdf_loss(a)\ns = """two\nlines"""\ny = signed_distance(p, q)\nz = L.nothing_here\nw = np.sum(x)'
    lines = book.highlight_lines(code, "python", link)
    assert len(lines) == len(code.split("\n"))
    assert 'href="core.losses#sdf_loss"' in lines[0]
    assert 'href="core.sdf#signed_distance"' in lines[3]
    assert 'href="core.losses#"' in lines[4]  # an unknown name of a known module: the module's page
    assert "href" not in lines[5]  # numpy is not the package
    assert re.sub(r"<[^>]+>", "", lines[1]) == 's = """two'  # the string spans two lines, each whole
    assert book.resolve(["L", "sdf_loss"], names, modules)[2] == "sdf_loss"
    assert modules["core.losses"].symbols["sdf_loss"] > 1


def test_tag_solutions_marks_only_solution_cells():
    nb = {"cells": [{"cell_type": "code", "metadata": {"nbgrader": {"solution": True}}, "source": ""},
                    {"cell_type": "code", "metadata": {"nbgrader": {"solution": False, "grade": True}}, "source": ""},
                    {"cell_type": "markdown", "metadata": {}, "source": ""}]}
    tagged = book.tag_solutions(nb)["cells"]
    assert [c["metadata"].get("tags", []) for c in tagged] == [[book.SOLUTION_TAG], [], []]


def _fake_site(tmp_path):
    site = SimpleNamespace(modules=book.index_package(), slugs={"", "index", "lesson"}, images=set())
    site.image = lambda value, mime: "_static/img/" + Path(value.get("path", "")).name if value.get("path") else None
    site.public_text = lambda path: ""
    return site


def _code_block(code, tags=(), outputs=()):
    return {"type": "block", "kind": "notebook-code", "data": {"tags": list(tags)}, "identifier": "c1",
            "children": [{"type": "code", "lang": "python", "value": code},
                         {"type": "outputs", "children": [{"type": "output", "jupyter_data": o} for o in outputs]}]}


def test_solution_folds_with_its_output(tmp_path):
    r = book.PageRenderer(_fake_site(tmp_path), "lesson", book.Names({"losses": "core.losses"}))
    block = _code_block("answer = None\n### BEGIN SOLUTION\nanswer = losses.depth_loss(a, b)\n### END SOLUTION",
                        [book.SOLUTION_TAG], [{"output_type": "stream", "name": "stdout", "text": "0.4242\n"}])
    out = r.node(block)
    details = re.findall(r'<details class="solution">.*?</details>', out, re.S)
    assert len(details) == 2, out  # the solution's code, and the output it printed
    assert "depth_loss" in details[0] and "0.4242" in details[1]
    outside = re.sub(r'<details class="solution">.*?</details>', "", out, flags=re.S)
    assert "depth_loss" not in outside and "0.4242" not in outside and "answer" in outside
    assert "BEGIN SOLUTION" not in out
    assert ("core.losses", "depth_loss") in r.used


def test_inline_code_links_to_the_source_line(tmp_path):
    r = book.PageRenderer(_fake_site(tmp_path), "lesson", book.Names())
    line = book.index_package()["core.losses"].symbols["sdf_loss"]
    for text in ("losses.sdf_loss", "losses.sdf_loss(pred, gt)", "geodepth_lite.core.losses.sdf_loss"):
        assert f'href="source/core.losses.html#L{line}"' in r.n_inlineCode({"value": text}), text
    assert 'href="source/core.losses.html"' in r.n_inlineCode({"value": "geodepth_lite/core/losses.py"})
    for text in ("losses", "numpy.sum", "losses.no_such_name", "python -m geodepth_lite train"):
        assert "href" not in r.n_inlineCode({"value": text}), text


def test_links_to_files_outside_the_book_are_named_not_linked(tmp_path):
    r = book.PageRenderer(_fake_site(tmp_path), "lesson", book.Names())
    assert r.n_link({"url": "/lesson#goal", "children": [{"type": "text", "value": "x"}]}) == \
        '<a href="lesson.html#goal">x</a>'
    assert "<a" not in r.n_link({"url": "CHANGELOG.md", "children": [{"type": "text", "value": "log"}]})
    assert 'href="source/utils.html#L3"' in r.n_link({"url": "../geodepth_lite/utils.py#L3", "children": []})


def test_check_out_refusals(tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    with pytest.raises(OSError, match="a file of that name exists"):
        book.check_out(a_file)
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "notes.txt").write_text("mine")
    with pytest.raises(OSError, match="did not write"):
        book.check_out(theirs)
    repo = tmp_path / "repo"
    (repo / "site").mkdir(parents=True)
    (repo / "site" / "index.html").write_text("tracked")
    (repo / "site" / book.MARKER).write_text("{}")
    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    subprocess.run(["git", "-C", str(repo), "add", "site/index.html"], check=True)
    with pytest.raises(OSError, match="tracked by git"):
        book.check_out(repo / "site")
    ours = tmp_path / "ours"
    ours.mkdir()
    (ours / book.MARKER).write_text("{}")
    (ours / "index.html").write_text("old")
    book.check_out(ours)  # written by the book command before: accepted
    book.check_out(tmp_path / "new")  # does not exist yet: accepted


def test_missing_node_is_one_line(tmp_path, monkeypatch, capsys):
    bare = tmp_path / "bin"
    bare.mkdir()
    with pytest.raises(book.BookError, match="needs Node.js 18 or newer"):
        book.check_node(str(bare))
    old = bare / "node"
    old.write_text("#!/bin/sh\necho v16.20.0\n")
    old.chmod(0o755)
    with pytest.raises(book.BookError, match="this one is v16.20.0"):
        book.check_node(str(bare))
    old.unlink()
    monkeypatch.setenv("PATH", str(bare))
    out = tmp_path / "site"
    assert cli.main(["book", "--out", str(out)]) == 2
    one_line_error(capsys, "Node.js 18 or newer", "no node is on PATH")
    assert not out.exists()


# a MyST build of one page, written by the test instead of jupyter-book: the rendering runs without Node
def _fake_myst(pages_content, png=b"\x89PNG\r\n\x1a\n"):
    def run_myst(project, timeout=0):
        site = project / "_build" / "site"
        (site / "content").mkdir(parents=True)
        (site / "public").mkdir()
        (site / "public" / "fig.png").write_bytes(png)
        pages = [{"slug": slug, "title": slug, "level": 1} for slug in pages_content]
        (site / "config.json").write_text(json.dumps({"projects": [{"index": "index", "pages": pages}]}))
        for slug, mdast in pages_content.items():
            loc = "/index.md" if slug == "index" else f"/notebooks/{slug}.ipynb"
            (site / "content" / f"{slug}.json").write_text(json.dumps(
                {"kind": "Notebook", "location": loc, "frontmatter": {"title": f"Title {slug}"}, "mdast": mdast}))
        return site
    return run_myst


LESSON = {"type": "root", "children": [
    {"type": "block", "kind": "notebook-content", "children": [
        {"type": "paragraph", "children": [
            {"type": "text", "value": "See "},
            {"type": "inlineMath", "value": "x^2", "html": '<span class="katex">x2</span>'}]}]},
    _code_block("from geodepth_lite.core import losses\nv = losses.depth_loss(a, b)",
                outputs=[{"output_type": "display_data", "data": {"image/png": {"path": "/fig.png"}}}])]}


def _lesson_nb(tmp_path):
    nb = tmp_path / "nbs" / "lesson.ipynb"
    nb.parent.mkdir()
    nb.write_text(json.dumps({"cells": [{"cell_type": "code", "metadata": {}, "outputs": [],
                                         "source": "from geodepth_lite.core import losses\n"
                                                   "v = losses.depth_loss(a, b)"}],
                              "metadata": {}, "nbformat": 4, "nbformat_minor": 5}))
    return nb


def _few_modules(monkeypatch):
    """Source pages for two modules only: the build tests stay fast."""
    few = {k: v for k, v in book.index_package().items() if k in ("core.losses", "utils")}
    monkeypatch.setattr(book, "index_package", lambda: few)


def test_build_renders_and_marks_complete(tmp_path, monkeypatch):
    _few_modules(monkeypatch)
    monkeypatch.setattr(book, "run_myst", _fake_myst({"index": {"type": "root", "children": []}, "lesson": LESSON}))
    monkeypatch.setattr(book, "check_node", lambda path=None: "node")
    out = tmp_path / "site"
    summary = book.build(out, notebooks=[_lesson_nb(tmp_path)], docs=[], readme=None, katex=False, log=lambda m: None)
    assert summary["pages"] == ["index.html", "lesson.html"] and summary["figures"] == 1
    assert book.read_marker(out)["complete"] is True
    page = (out / "lesson.html").read_text()
    line = book.index_package()["core.losses"].symbols["depth_loss"]
    assert f'href="source/core.losses.html#L{line}"' in page
    assert '<img src="_static/img/fig.png"' in page and (out / "_static/img/fig.png").is_file()
    assert 'id="L1"' in (out / "source/core.losses.html").read_text()
    assert "lesson.html" in (out / "source/core.losses.html").read_text()  # the source page names the lesson using it
    assert not (out / book.NEW_DIR).exists() and not (out / ".lock").exists()
    # the lesson's notebook to download, beside its page, and the page in the search index
    assert 'href="notebooks/lesson.ipynb" download' in page and summary["downloads"] == {
        "lesson.ipynb": "notebooks/lesson.ipynb"}
    assert (out / "notebooks/lesson.ipynb").read_bytes() == (tmp_path / "nbs/lesson.ipynb").read_bytes()
    index = book.book_reader.read_search_index((out / "_static" / book.SEARCH_INDEX).read_text(encoding="utf-8"))
    assert [p["u"] for p in index["pages"]][:2] == ["index.html", "lesson.html"]
    assert {"notebooks/lesson.ipynb", "_static/search-index.js", "_static/book.js"} <= set(
        book.read_marker(out)["files"])
    book.build(out, notebooks=[tmp_path / "nbs/lesson.ipynb"], docs=[], readme=None, katex=False,
               log=lambda m: None)  # a second build replaces the first
    assert book.read_marker(out)["complete"] is True


def test_failed_build_leaves_no_site(tmp_path, monkeypatch):
    _few_modules(monkeypatch)
    monkeypatch.setattr(book, "check_node", lambda path=None: "node")
    nb = _lesson_nb(tmp_path)

    def broken(project, timeout=0):
        raise book.BookError("cannot build the book: jupyter-book build failed (exit status 1): boom")

    monkeypatch.setattr(book, "run_myst", broken)
    new = tmp_path / "new" / "site"
    with pytest.raises(book.BookError, match="boom"):
        book.build(new, notebooks=[nb], docs=[], readme=None, katex=False, log=lambda m: None)
    assert not (tmp_path / "new").exists()  # the folders it made are gone again

    # a complete site stays as it was when a rebuild fails before it is published
    monkeypatch.setattr(book, "run_myst", _fake_myst({"index": {"type": "root", "children": []}, "lesson": LESSON}))
    out = tmp_path / "site"
    book.build(out, notebooks=[nb], docs=[], readme=None, katex=False, log=lambda m: None)
    before = (out / "lesson.html").read_text()
    monkeypatch.setattr(book.Site, "render_sources", lambda self: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        book.build(out, notebooks=[nb], docs=[], readme=None, katex=False, log=lambda m: None)
    assert (out / "lesson.html").read_text() == before and book.read_marker(out)["complete"] is True
    assert not (out / book.NEW_DIR).exists()

    # cut off while the new site replaces the old: no page left, and the marker says incomplete
    monkeypatch.undo()
    _few_modules(monkeypatch)
    monkeypatch.setattr(book, "check_node", lambda path=None: "node")
    monkeypatch.setattr(book, "run_myst", _fake_myst({"index": {"type": "root", "children": []}, "lesson": LESSON}))
    real_replace = os.replace
    calls = []

    def failing_replace(a, b):
        calls.append(a)
        if len(calls) == 2:
            raise OSError(28, "No space left on device")
        return real_replace(a, b)

    monkeypatch.setattr(book.os, "replace", failing_replace)
    with pytest.raises(OSError):
        book.build(out, notebooks=[nb], docs=[], readme=None, katex=False, log=lambda m: None)
    assert book.read_marker(out)["complete"] is False
    assert sorted(p.name for p in out.iterdir()) == [book.MARKER]


def _fake_build(tmp_path, monkeypatch, pages=("index", "lesson")):
    """``book.build`` with a one-notebook MyST build of ``pages`` written by the test (no Node.js)."""
    _few_modules(monkeypatch)
    monkeypatch.setattr(book, "check_node", lambda path=None: "node")
    monkeypatch.setattr(book, "check_jupyter_book", lambda: None)
    nb = tmp_path / "nbs" / "lesson.ipynb"
    if not nb.exists():
        _lesson_nb(tmp_path)

    real_build = book.build

    def build(out, **kw):
        content = {slug: LESSON if slug == "lesson" else {"type": "root", "children": []} for slug in pages}
        monkeypatch.setattr(book, "run_myst", _fake_myst(content))
        return real_build(out, notebooks=[nb], docs=[], readme=None, katex=False, log=lambda m: None)
    return build


def _tree(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_rebuild_keeps_the_users_files_and_removes_only_its_own(tmp_path, monkeypatch, capsys):
    build = _fake_build(tmp_path, monkeypatch, pages=("index", "lesson", "extra"))
    out = tmp_path / "site"
    build(out)
    marker = book.read_marker(out)
    assert marker["complete"] is True
    assert marker["files"]["lesson.html"] == book.regular_file_sha256(out / "lesson.html")
    assert set(marker["files"]) == {p for p in _tree(out) if p != book.MARKER}  # every file it wrote, no other
    (out / "CNAME").write_text("book.example.org\n")
    (out / "my_slides").mkdir()
    (out / "my_slides" / "week1.pdf").write_bytes(b"%PDF-1.4 slides")
    (out / "_static" / "custom.css").write_text("body{}")  # the user's file in a folder of the book's
    mine = {k: v for k, v in _tree(out).items() if k in ("CNAME", "my_slides/week1.pdf", "_static/custom.css")}
    build = _fake_build(tmp_path, monkeypatch, pages=("index", "lesson"))  # the new site has no extra page
    build(out)
    after = _tree(out)
    assert {k: after.get(k) for k in mine} == mine  # kept, byte for byte
    assert "extra.html" not in after and "lesson.html" in after  # its own old page removed
    assert book.read_marker(out)["complete"] is True and not any(p.name.startswith(book.NEW_DIR) for p in
                                                                 out.iterdir())
    # a page of the book's that the user changed is theirs now: refused with one line, nothing changed
    (out / "lesson.html").write_text("my notes on the lesson")
    before = _tree(out)
    monkeypatch.setattr(book, "build", lambda out, **kw: build(out))
    assert cli.main(["book", "--out", str(out)]) == 2
    one_line_error(capsys, str(out / "lesson.html"), "did not write it")
    assert _tree(out) == before


def test_a_forged_marker_grants_nothing(tmp_path, monkeypatch):
    build = _fake_build(tmp_path, monkeypatch)
    outside = tmp_path / "outside.txt"
    outside.write_text("not the book's")
    digest = book.regular_file_sha256(outside)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "book.css").write_text("mine")
    forged = [{"complete": True}, {"complete": True, "files": {"thesis.tex": None}},
              {"complete": True, "files": {"../outside.txt": digest, "_static/../../outside.txt": digest}},
              {"complete": True, "files": {"_static/book.css": book.regular_file_sha256(elsewhere / "book.css")}}]
    for k, marker in enumerate(forged):
        folder = tmp_path / f"forged{k}"
        folder.mkdir()
        (folder / "thesis.tex").write_text("\\documentclass{article} my thesis")
        if marker.get("files", {}).get("thesis.tex", 1) is None:
            marker["files"]["thesis.tex"] = book.regular_file_sha256(folder / "thesis.tex")  # the right hash, even
        if k == 3:
            (folder / "_static").symlink_to(elsewhere, target_is_directory=True)
        (folder / book.MARKER).write_text(json.dumps(marker))
        before = _tree(folder)
        try:
            build(folder)
        except OSError as exc:  # a link in the way of the site: refused
            assert k == 3 and "_static" in str(exc)
        after = _tree(folder)
        assert {p: after.get(p) for p in before if p != book.MARKER} == {
            p: v for p, v in before.items() if p != book.MARKER}, k
        assert outside.read_text() == "not the book's" and (elsewhere / "book.css").read_text() == "mine"
    # a marker naming the user's page with a hash that is not its own: the page is in the way, refused
    folder = tmp_path / "forged_page"
    folder.mkdir()
    (folder / "index.html").write_text("my home page")
    (folder / book.MARKER).write_text(json.dumps({"complete": True, "files": {"index.html": "0" * 64}}))
    with pytest.raises(OSError, match="index.html is in the way"):
        build(folder)
    assert (folder / "index.html").read_text() == "my home page"


def test_the_forged_marker_check_fails_on_a_book_that_trusts_its_marker(tmp_path, monkeypatch):
    """The planted defect: owned_files taking every name the marker lists. The check above would see
    thesis.tex go."""
    build = _fake_build(tmp_path, monkeypatch)
    folder = tmp_path / "forged"
    folder.mkdir()
    (folder / "thesis.tex").write_text("my thesis")
    (folder / book.MARKER).write_text(json.dumps({"complete": True, "files": {"thesis.tex": "0" * 64}}))
    monkeypatch.setattr(book, "owned_files", lambda out, marker: dict(marker["files"]))
    monkeypatch.setattr(book, "_remove_owned", lambda out, rel, digest: (Path(out) / rel).unlink())
    build(folder)
    assert not (folder / "thesis.tex").exists()


def test_staging_left_by_a_killed_build_is_removed_by_the_next(tmp_path, monkeypatch):
    """kill -9 of a build while it renders leaves its MyST project in the temporary folder and its half
    site in the output folder; the next build removes both (their process is gone) and nothing else."""
    temp = tmp_path / "temp"
    temp.mkdir()
    out = tmp_path / "site"
    script = f"""
import sys, tempfile, time
sys.path.insert(0, {str(Path(__file__).parent)!r})
tempfile.tempdir = {str(temp)!r}
import pytest
import test_book
from geodepth_lite.workbook import book
mp = pytest.MonkeyPatch()
build = test_book._fake_build(__import__("pathlib").Path({str(tmp_path)!r}), mp)
mp.setattr(book.Site, "render_sources", lambda self: (print("rendering", flush=True), time.sleep(300)))
build(__import__("pathlib").Path({str(out)!r}))
"""
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(Path(book.ROOT))})
    try:
        assert proc.stdout.readline().strip() == "rendering"
    finally:
        proc.kill()  # SIGKILL: no clean-up runs
        proc.wait()
    left = [p.name for p in temp.iterdir()] + [p.name for p in out.iterdir()]
    assert f"{book.NEW_DIR}-{proc.pid}" in left and any(n.startswith(f"geodepth-book-{proc.pid}-") for n in left)
    alive = temp / f"geodepth-book-{os.getppid()}-abc123"  # a live process's: kept
    alive.mkdir()
    (temp / "geodepth-book-notes").mkdir()  # not a staging name: kept
    monkeypatch.setattr(book.tempfile, "tempdir", str(temp))
    _fake_build(tmp_path, monkeypatch)(out)
    assert sorted(p.name for p in temp.iterdir()) == sorted([alive.name, "geodepth-book-notes"])
    assert not any(p.name.startswith(book.NEW_DIR) for p in out.iterdir())
    assert book.read_marker(out)["complete"] is True


def test_a_full_disk_names_the_file_and_keeps_the_old_site(tmp_path, monkeypatch, capsys):
    build = _fake_build(tmp_path, monkeypatch)
    out = tmp_path / "site"
    build(out)
    before = _tree(out)
    real_write = Path.write_bytes

    def full(self, data):
        if self.name == "lesson.html":
            raise OSError(28, "No space left on device")  # as the kernel reports it: no file named
        return real_write(self, data)

    monkeypatch.setattr(Path, "write_bytes", full)
    monkeypatch.setattr(book, "build", lambda out, **kw: build(out))
    assert cli.main(["book", "--out", str(out)]) == 2
    line = one_line_error(capsys, "no space left on device", "lesson.html")
    assert re.search(r"cannot write \S*/\.geodepth-book-new-\d+/lesson\.html: no space left on device$", line)
    assert _tree(out) == before and not any(p.name.startswith(book.NEW_DIR) for p in out.iterdir())


def test_katex_tarball_is_checked_and_bounded(tmp_path):
    cache = tmp_path / "katex.tgz"
    cache.write_bytes(b"not the package")
    failing_npm = tmp_path / "npm"
    failing_npm.write_text("#!/bin/sh\necho 'npm error network unreachable' >&2\nexit 1\n")
    failing_npm.chmod(0o755)
    got, why = book.fetch_katex(cache, npm=str(failing_npm))
    assert got is None and "network unreachable" in why
    # a tarball with a path out of its folder and a link: only the two expected regular files come out
    tgz = tmp_path / "crafted.tgz"
    with tarfile.open(tgz, "w:gz") as tar:
        for name, data in (("package/dist/katex.min.css", b".katex{}"),
                           ("package/dist/fonts/KaTeX_Main-Regular.woff2", b"font"),
                           ("package/dist/fonts/../../../evil.css", b"evil")):
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
        link = tarfile.TarInfo("package/dist/fonts/KaTeX_Link.woff")
        link.type, link.linkname = tarfile.SYMTYPE, "/etc/passwd"
        tar.addfile(link)
    dest = book.extract_katex(tgz, tmp_path / "k")
    found = sorted(p.relative_to(dest).as_posix() for p in dest.rglob("*") if p.is_file())
    assert found == ["fonts/KaTeX_Main-Regular.woff2", "katex.min.css"]
    assert not (tmp_path / "evil.css").exists()


# --------------------------------------------------------------------------- HTML the book did not write

VECTORS = [  # classic ways to run script through HTML that passes for harmless
    '<img src=x onerror="alert(1)">',
    '<IMG SRC=x OnError=alert(1)//>',
    "<script>alert(1)</script>",
    "<scr<script>ipt>alert(1)</script>",
    '<svg onload="alert(1)"><circle r="1"/></svg>',
    '<svg><script>alert(1)</script></svg>',
    '<a href="javascript:alert(1)">x</a>',
    '<a href="jav&#x09;ascript:alert(1)">x</a>',
    '<a href=" &#14;javascript:alert(1)">x</a>',
    '<a href="JaVaScRiPt&colon;alert(1)">x</a>',
    '<a href="data:text/html;base64,PHNjcmlwdD5hbGVydCgxKTwvc2NyaXB0Pg==">x</a>',
    '<img src="data:image/svg+xml;base64,PHN2ZyBvbmxvYWQ9YWxlcnQoMSk+">',
    '<div style="width: expression(alert(1))">x</div>',
    '<div style="background:url(javascript:alert(1))">x</div>',
    "<style>@import 'javascript:alert(1)';</style>",
    '<table><tr><td background="javascript:alert(1)">x</td></tr></table>',
    '<noscript><p title="</noscript><img src=x onerror=alert(1)>"></noscript>',
    '<iframe src="javascript:alert(1)"></iframe>',
    '<object data="javascript:alert(1)"></object><embed src="javascript:alert(1)">',
    '<math><mtext><table><mglyph><style><img src=x onerror=alert(1)>',
    '<details open ontoggle="alert(1)">x</details>',
    '<form><button formaction="javascript:alert(1)">x</button></form>',
    '<meta http-equiv="refresh" content="0;url=javascript:alert(1)">',
    '<base href="javascript:alert(1)//">',
]


def _script_risks(doc: str) -> list[str]:
    """What in ``doc`` can run script when a browser shows it: event handlers, style, script-bearing elements,
    URLs of a scheme other than http(s)/mailto (data: images of a raster type excepted)."""
    from html.parser import HTMLParser

    risks = []

    class Finder(HTMLParser):
        def handle_starttag(self, tag, attrs):
            if tag in ("script", "style", "svg", "math", "iframe", "object", "embed", "meta", "base", "form",
                       "button", "noscript"):
                risks.append(tag)
            for name, value in attrs:
                squeezed = re.sub(r"[\x00-\x20]+", "", value or "").lower()
                if name.startswith("on") or name == "style":
                    risks.append(name)
                elif re.match(r"^[a-z][a-z0-9+.-]*:", squeezed) and not re.match(
                        r"^(https?:|mailto:|data:image/(png|jpeg|gif|webp);base64,)", squeezed):
                    risks.append(f"{name}={squeezed[:20]}")

    Finder(convert_charrefs=True).feed(doc)
    return risks + (["<script"] if "<script" in doc.lower() else [])


def test_sanitiser_removes_every_classic_vector():
    for vector in VECTORS:
        assert _script_risks(vector), vector  # the check sees the danger in the raw vector ...
        clean = book.sanitise_html(vector)
        assert not _script_risks(clean), (vector, clean)  # ... and none is left after sanitising
    # what outputs need stays: a pandas-like table, text formatting, a link, a raster data-URL image
    table = ('<table border="1" class="dataframe"><thead><tr><th>a</th></tr></thead><tbody><tr><td colspan="2">'
             '1 &lt; 2</td></tr></tbody></table><b>bold</b> <a href="https://example.org/x?a=1&amp;b=2">l</a>'
             '<img src="data:image/png;base64,iVBORw0KGgo=" alt="fig">')
    clean = book.sanitise_html(table)
    assert clean == table.replace('">l</a>', '" rel="noopener noreferrer nofollow">l</a>')
    assert book.sanitise_html("<p>open <b>bold") == "<p>open <b>bold</b></p>"  # closed, whole HTML
    # a value that breaks out of its quotes where it is written back unescaped: it stays one value
    breaking = '<a title=\'x" onmouseover="alert(1)\'>z</a>'
    assert _script_risks('<a title="x" onmouseover="alert(1)">z</a>') == ["onmouseover"]  # written back naively
    assert book.sanitise_html(breaking).startswith('<a title="x&quot; onmouseover=&quot;alert(1)"')
    assert not _script_risks(book.sanitise_html(breaking))


def test_a_planted_sanitiser_defect_is_caught():
    """The check of the test above fails on a sanitiser that keeps event handlers (a defect planted here)."""
    leaky = book._Sanitiser.handle_starttag

    def keeps_handlers(self, tag, attrs):
        leaky(self, tag, attrs)
        if tag in book.SAFE_TAGS and self.out and attrs:
            self.out[-1] = self.out[-1][:-1] + "".join(f' {k}="{v}"' for k, v in attrs if k.startswith("on")) + ">"

    book._Sanitiser.handle_starttag = keeps_handlers
    try:
        assert _script_risks(book.sanitise_html(VECTORS[0])) == ["onerror"]
    finally:
        book._Sanitiser.handle_starttag = leaky


def test_html_outputs_are_sanitised_or_sandboxed(tmp_path):
    r = book.PageRenderer(_fake_site(tmp_path), "lesson", book.Names())
    inline = r.output({"output_type": "display_data",
                       "data": {"text/html": {"content": '<img src=x onerror="alert(1)"><table><tr><td>t</td></tr>'
                                                         "</table>"}}})
    assert "onerror" not in inline and "<td>t</td>" in inline
    framed = r.output({"output_type": "display_data",
                       "data": {"text/html": {"content": "<p>x</p><script>alert(1)</script>"}}})
    assert framed.startswith('<iframe class="output-html" sandbox="" srcdoc="') and "<script" not in framed
    assert "allow-" not in framed  # no permission at all: no script, no same origin
    assert "onerror" not in r.n_html({"value": '<img src=y onerror="alert(1)">'})
    assert "<a" not in r.n_link({"url": "javascript:alert(1)", "children": [{"type": "text", "value": "x"}]})
    assert "<a" not in r.n_link({"url": " java\tscript:alert(1)", "children": []})
    assert r.n_link({"url": "https://example.org", "children": []}).startswith('<a href="https://example.org"')


# --------------------------------------------------------------------------- the real book in a browser


def _browser_missing() -> str:
    if not Path(CHROMIUM).is_file():
        return f"{CHROMIUM} is missing (Debian: apt-get install chromium)"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "the Python package playwright is missing (pip install -r environment.txt)"
    try:
        book.check_node()
        book.check_jupyter_book()
    except book.BookError as exc:
        return str(exc)
    return ""


@pytest.fixture(scope="module")
def served_book(tmp_path_factory):
    """The book built once from the checkout, served by a local http.server thread."""
    missing = _browser_missing()
    if missing:
        if os.environ.get(REQUIRE_ENV, "") not in ("", "0"):
            pytest.fail(f"{REQUIRE_ENV}=1, but the browser test cannot run: {missing}")
        pytest.skip(f"browser test: {missing}")
    out = tmp_path_factory.mktemp("book") / "site"
    summary = book.build(out, log=lambda m: None)

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(out)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield out, f"http://127.0.0.1:{server.server_port}", summary
    server.shutdown()
    server.server_close()


def test_the_real_books_marker_lists_every_file_it_wrote(served_book):
    """Every file of the built site is recorded with its SHA-256 under a name the book owns, so a rebuild
    can replace each one and nothing else."""
    out, _, _ = served_book
    files = book.read_marker(out)["files"]
    on_disk = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()} - {book.MARKER}
    assert set(files) == on_disk and len(files) > 20
    assert book.owned_files(out, book.read_marker(out)) == files  # every hash matches, every name is the book's


def _notebook_facts():
    """Per lesson notebook: whether its markdown has $...$ math, and the first line of each solution."""
    facts = {}
    for nb in book.lesson_notebooks():
        data = json.loads(nb.read_text(encoding="utf-8"))
        md = "\n".join("".join(c["source"]) for c in data["cells"] if c["cell_type"] == "markdown")
        public = "\n".join("\n".join(exercises._split_solutions("".join(c["source"]))[1]) for c in data["cells"])
        solutions = []
        for c in data["cells"]:
            if c["cell_type"] == "code" and c["metadata"].get("nbgrader", {}).get("solution"):
                lines = [ln for ln in exercises.solution_lines("".join(c["source"]))
                         if len(ln) > 12 and ln not in public]
                if lines:  # a line of the solution that the notebook shows nowhere else
                    solutions.append(lines[0])
        facts[nb.name] = {"math": bool(re.search(r"\$[^$\n]+\$", md)), "solutions": solutions}
    return facts


VISIBLE_TEXT = """() => {
  const body = document.querySelector('main').cloneNode(true);
  body.querySelectorAll('pre, code, .katex, script, style').forEach(e => e.remove());
  return body.textContent;
}"""


@pytest.fixture(scope="module")
def browsed(served_book):
    """Every page of the built book opened in chromium once: what each showed."""
    from playwright.sync_api import sync_playwright

    out, base, summary = served_book
    pages = sorted(p.relative_to(out).as_posix() for p in out.rglob("*.html"))
    report = {}
    with sync_playwright() as pw:
        ctx = pw.chromium.launch_persistent_context(str(out.parent / "profile"), executable_path=CHROMIUM,
                                                    args=CHROMIUM_ARGS, headless=True)
        page = ctx.new_page()
        problems = []
        page.on("console", lambda m: problems.append(f"console {m.type}: {m.text}") if m.type == "error" else None)
        page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
        page.on("requestfailed", lambda r: problems.append(f"request failed: {r.url}"))
        page.on("response", lambda r: problems.append(f"HTTP {r.status}: {r.url}") if r.status >= 400 else None)
        for rel in pages:
            problems.clear()
            response = page.goto(f"{base}/{rel}", wait_until="load")
            entry = {"status": response.status if response else None}
            entry["broken_images"] = page.evaluate(
                "() => [...document.images].filter(i => !(i.complete && i.naturalWidth > 0)).map(i => i.src)")
            entry["images"] = page.evaluate("() => document.images.length")
            entry["text"] = page.evaluate(VISIBLE_TEXT)
            entry["katex"] = page.evaluate("() => document.querySelectorAll('main .katex').length")
            entry["katex_font"] = page.evaluate(
                "() => { const k = document.querySelector('main .katex'); return k ? getComputedStyle(k).fontFamily"
                " : ''; }")
            entry["math_shown"] = page.evaluate(
                "() => [...document.querySelectorAll('main .katex')].filter(k => k.getBoundingClientRect().width > 0)"
                ".length")
            entry["views_3d"] = page.locator(".geodepth-3d").count()
            if entry["views_3d"]:  # plotly.js draws each view (it waits for the script at the page's end)
                page.wait_for_function(
                    "() => [...document.querySelectorAll('.geodepth-3d')].every(d => d.querySelector('.main-svg'))",
                    timeout=30000)
                entry["views_3d_drawn"] = page.evaluate(
                    "() => [...document.querySelectorAll('.geodepth-3d')].filter(d => d.querySelector('canvas')"
                    " && d.getBoundingClientRect().height > 100).length")
            if not rel.startswith(book.SOURCE + "/"):
                entry["folded_text"] = page.evaluate("() => document.querySelector('main').innerText")
                entry["solutions"] = page.locator("details.solution").count()
                entry["closed"] = page.evaluate(
                    "() => [...document.querySelectorAll('details.solution')].every(d => !d.open)")
                for summary_el in page.locator("details > summary").all():
                    summary_el.click()
                entry["open_text"] = page.evaluate("() => document.querySelector('main').innerText")
                entry["opened"] = page.evaluate(
                    "() => [...document.querySelectorAll('details.solution')].every(d => d.open)")
            entry["problems"] = list(problems)
            report[rel] = entry
        ctx.close()
    return report, summary


def test_every_page_loads_without_errors(browsed):
    report, summary = browsed
    assert len(report) >= len(summary["pages"]) + summary["source_pages"]
    bad = {rel: (e["status"], e["problems"]) for rel, e in report.items() if e["status"] != 200 or e["problems"]}
    assert not bad


def test_no_missing_image(browsed):
    report, summary = browsed
    assert not {rel: e["broken_images"] for rel, e in report.items() if e["broken_images"]}
    assert summary["figures"] > 0 and sum(e["images"] for e in report.values()) >= summary["figures"]


def test_no_raw_markdown(browsed):
    report, _ = browsed
    raw = {}
    for rel, e in report.items():
        found = [m for m in ("$$", "**", "```", ":::", "\\frac", "\\mathbf") if m in e["text"]]
        found += re.findall(r"\$[^$\s][^$\n]{0,40}\$", e["text"])  # inline math left as $...$
        if found:
            raw[rel] = found
    assert not raw


def test_math_is_typeset(browsed):
    report, summary = browsed
    facts = _notebook_facts()
    assert sum(f["math"] for f in facts.values()) >= 1
    for name, f in facts.items():
        e = report[summary["lesson_pages"][name]]
        if f["math"]:
            assert e["katex"] > 0 and e["math_shown"] == e["katex"], name
            if summary["katex"]:  # KaTeX's style sheet and fonts are in use
                assert "KaTeX_Main" in e["katex_font"], (name, e["katex_font"])


def test_solutions_are_folded_until_clicked(browsed):
    report, summary = browsed
    facts = _notebook_facts()
    assert sum(len(f["solutions"]) for f in facts.values()) >= 1
    for name, f in facts.items():
        e = report[summary["lesson_pages"][name]]
        assert e["solutions"] >= len(f["solutions"]) and e["closed"] and e["opened"], name
        for first_line in f["solutions"]:
            assert first_line not in e["folded_text"], (name, first_line)
            assert first_line in e["open_text"], (name, first_line)


def test_interactive_3d_views_are_drawn(browsed):
    """Every output that holds a plotly figure in a notebook is drawn on its page, offline (WebGL canvas)."""
    report, summary = browsed
    stored = {nb.name: sum(book.recon.PLOTLY_MIME in o.get("data", {}) for c in
                           json.loads(nb.read_text(encoding="utf-8"))["cells"] for o in c.get("outputs", []))
              for nb in book.lesson_notebooks()}
    assert sum(stored.values()) >= 1  # notebook 07 has views to turn
    for name, n in stored.items():
        e = report[summary["lesson_pages"][name]]
        assert e["views_3d"] == n and e.get("views_3d_drawn", 0) == n, (name, n, e["views_3d"])


# --------------------------------------------------------------------------- planted HTML in a browser

PAYLOAD = "window.__planted = (window.__planted || 0) + 1; new Image().src = '/ran-{0}'; alert('{0}');"


def _planted_notebook(folder: Path) -> Path:
    """A notebook whose outputs (and one markdown cell) carry script in the ways an output can: each payload,
    if it runs, sets a global, asks the server for /ran-<name> and opens a dialog."""
    def html_output(doc):
        return {"output_type": "display_data", "metadata": {}, "data": {"text/html": doc, "text/plain": "x"}}

    outputs = [
        html_output(f'<img src="x" onerror="{PAYLOAD.format("onerror")}"><table><tr><td>planted table</td></tr>'
                    "</table>"),
        html_output(f"<p>framed output</p><script>{PAYLOAD.format('script')}</script>"),
        html_output(f'<svg onload="{PAYLOAD.format("svg")}"></svg><a href="javascript:{PAYLOAD.format("href")}">'
                    "planted link</a>"),
    ]
    cells = [{"cell_type": "markdown", "metadata": {},
              "source": f'# Planted\n\n<img src="y" onerror="{PAYLOAD.format("markdown")}">\n'},
             {"cell_type": "code", "metadata": {}, "execution_count": 1, "source": "show()", "outputs": outputs}]
    nb = folder / "00_planted.ipynb"
    nb.write_text(json.dumps({"cells": cells, "metadata": {}, "nbformat": 4, "nbformat_minor": 5}))
    return nb


CONTROL = ("<!DOCTYPE html><html><body><img src=\"x\" onerror=\"{0}\">"
           "<iframe srcdoc=\"<script>{1}</script>\"></iframe></body></html>")


@pytest.fixture(scope="module")
def planted_site(tmp_path_factory):
    """A book of one notebook with planted HTML outputs, built by jupyter-book, served with every request
    recorded; and a control page (the same payloads unescaped) that shows the payloads do run unguarded."""
    missing = _browser_missing()
    if missing:
        if os.environ.get(REQUIRE_ENV, "") not in ("", "0"):
            pytest.fail(f"{REQUIRE_ENV}=1, but the browser test cannot run: {missing}")
        pytest.skip(f"browser test: {missing}")
    tmp = tmp_path_factory.mktemp("planted")
    with pytest.MonkeyPatch.context() as mp:
        _few_modules(mp)
        out = tmp / "site"
        summary = book.build(out, notebooks=[_planted_notebook(tmp)], docs=[], readme=None, katex=False,
                             log=lambda m: None)
    control = html.escape(PAYLOAD.format("control-script"))
    (tmp / "control.html").write_text(CONTROL.format(html.escape(PAYLOAD.format("control-onerror")), control))
    requests = []

    class Recording(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

        def do_GET(self):
            requests.append(self.path)
            super().do_GET()

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Recording, directory=str(tmp)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{server.server_port}", summary, requests
    server.shutdown()
    server.server_close()


def _open_and_watch(base: str, rel: str, requests: list) -> dict:
    """Open ``rel`` in chromium, click every link, wait, and report what ran: dialogs, the global, /ran-* requests."""
    from playwright.sync_api import sync_playwright

    requests.clear()
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        page = browser.new_page()
        dialogs = []
        page.on("dialog", lambda d: (dialogs.append(d.message), d.dismiss()))
        page.goto(f"{base}/{rel}", wait_until="load")
        page.wait_for_timeout(1500)
        for link in page.locator("main a").all():
            if "planted" in (link.inner_text() or ""):
                link.click()
        page.wait_for_timeout(500)
        seen = {"dialogs": dialogs, "global": page.evaluate("() => window.__planted === undefined ? null : 1"),
                "frames": page.evaluate(
                    "() => [...document.querySelectorAll('iframe')].map(f => f.getAttribute('sandbox'))"),
                "text": page.evaluate("() => document.body.innerText"),
                "ran": sorted({r for r in requests if r.startswith("/ran-")})}
        browser.close()
    return seen


def test_planted_html_in_outputs_cannot_run_script(planted_site):
    base, summary, requests = planted_site
    control = _open_and_watch(base, "control.html", requests)  # the watch sees a payload that runs
    assert control["ran"] == ["/ran-control-onerror", "/ran-control-script"] and control["dialogs"], control
    seen = _open_and_watch(base, "site/" + summary["lesson_pages"]["00_planted.ipynb"], requests)
    assert seen["ran"] == [] and seen["dialogs"] == [] and seen["global"] is None, seen
    assert seen["frames"] == [""]  # the output with a script: in an iframe sandboxed of every permission
    assert "planted table" in seen["text"] and "planted link" in seen["text"]  # the harmless part is shown


# --------------------------------------------------------------------------- printed tables, pieces for the reader

def _matrix(table_html: str) -> list[list[str]]:
    """The cell texts of an HTML table, row by row (read with the standard library's parser)."""
    from html.parser import HTMLParser

    rows: list[list[str]] = []

    class Cells(HTMLParser):
        cell = None

        def handle_starttag(self, tag, attrs):
            if tag == "tr":
                rows.append([])
            elif tag in ("td", "th"):
                self.cell = []

        def handle_endtag(self, tag):
            if tag in ("td", "th"):
                rows[-1].append("".join(self.cell))
                self.cell = None

        def handle_data(self, data):
            if self.cell is not None:
                self.cell.append(data)

    Cells(convert_charrefs=True).feed(table_html)
    return rows


PRINTED = ("| case | lambda2 | note |\n|:---|---:|:-:|\n| **teach** | 0.003 | `predict` a \\| b |\n"
           "| 2 | 1 | <script>x</script> |")
PRINTED_CELLS = [["case", "lambda2", "note"], ["teach", "0.003", "predict a | b"], ["2", "1", "<script>x</script>"]]


def test_a_printed_pipe_table_becomes_a_table():
    table = book.book_reader.pipe_table(PRINTED.split("\n"))
    assert _matrix(table) == PRINTED_CELLS
    assert "<strong>teach</strong>" in table and "<code>predict</code>" in table
    assert "<script>" not in table and "&lt;script&gt;" in table  # the cell text is escaped
    assert 'style="text-align:left"' in table and 'style="text-align:right"' in table
    assert 'style="text-align:center"' in table
    blocks = book.book_reader.text_blocks("12 runs ready\n" + PRINTED + "\n6 of 6 within\n")
    assert [k for k, _ in blocks] == ["text", "table", "text"] and blocks[0][1] == "12 runs ready"
    out = book.book_reader.printed_html("12 runs ready\n" + PRINTED + "\n", "stdout")
    assert out.startswith('<pre class="stdout">12 runs ready</pre><div class="printed-table"><table')


def test_malformed_pipe_tables_stay_text():
    ragged = "| a | b |\n|---|---|\n| 1 | 2 | 3 |"  # a body row with a cell more than the header
    no_separator = "| a | b |\n| 1 | 2 |\n| 3 | 4 |"
    short_separator = "| a | b | c |\n|---|---|\n| 1 | 2 | 3 |"
    not_dashes = "| a | b |\n|-x-|---|\n| 1 | 2 |"
    header_only = "| a | b |"
    for text in (ragged, no_separator, short_separator, not_dashes, header_only, "a | b\n---|---\n1 | 2"):
        assert book.book_reader.pipe_table(text.split("\n")) is None, text
        pre = f'<pre class="stdout">{html.escape(text, quote=False)}</pre>'
        assert book.book_reader.printed_html(text, "stdout") == pre
    # a ragged table in a printed block leaves the well-formed one beside it a table (notebook 05 prints both)
    mixed = book.book_reader.text_blocks(ragged + "\nbetween\n" + PRINTED)
    assert [k for k, _ in mixed] == ["text", "table"] and mixed[0][1] == ragged + "\nbetween"


def test_the_table_check_fails_on_swapped_cells(monkeypatch):
    """The planted defect: a converter that swaps a row's first two cells; the check above sees it."""
    real = book.book_reader.pipe_cells
    monkeypatch.setattr(book.book_reader, "pipe_cells", lambda line: (lambda c: [c[1], c[0], *c[2:]])(real(line)))
    table = book.book_reader.pipe_table(PRINTED.split("\n"))
    assert table is not None and _matrix(table) != PRINTED_CELLS
    # and a converter that cuts every row to two cells takes a ragged table for a table: the check above sees it
    monkeypatch.setattr(book.book_reader, "pipe_cells", lambda line: real(line)[:2])
    assert book.book_reader.pipe_table("| a | b |\n|---|---|\n| 1 | 2 | 3 |".split("\n")) is not None


def test_page_sections_for_the_search_index():
    body = ('<h1 id="t">Title</h1><p>Intro <span class="katex"><span>x2</span></span> text</p><pre>code_only</pre>'
            '<h2 id="a">Part <code>A</code></h2><p>alpha &amp; beta</p><details class="solution"><summary>S'
            '</summary><pre>secret</pre></details><nav class="page-toc"><a href="#a">Part A</a></nav>'
            '<img src="x.png"><h3>no id</h3><p>gamma</p>')
    assert book.book_reader.page_sections(body) == [["t", "Title", "Intro text"],
                                                    ["a", "Part A", "alpha & beta no id gamma"]]
    js = book.book_reader.search_index_js([{"t": "T", "u": "p.html", "s": [["a", "h", "</script> x"]]}])
    assert book.book_reader.read_search_index(js)["pages"][0]["s"][0][2] == "</script> x"


def test_the_landing_page_shows_the_readmes_key_figure():
    readme = book.README.read_text(encoding="utf-8")
    name, section, caption = book.book_reader.key_figure_ref(readme)
    assert name == "05_ablation.ipynb" and section and caption.startswith("[notebook 05](")
    nb = json.loads((exercises.NOTEBOOK_DIR / name).read_text(encoding="utf-8"))
    png = book.book_reader.section_figure(nb, section)
    assert png is not None and png.startswith(b"\x89PNG\r\n\x1a\n")
    assert book.book_reader.section_figure(nb, section + " (no such section)") is None
    purpose = book.book_reader.readme_purpose(readme)
    assert purpose and "workbook" in purpose[0] and not any("build the book" in p.lower() for p in purpose)
    md = book.book_reader.landing_markdown(purpose, [(name, "05 · The ablation")], ("key-figure.png", caption), False)
    assert "![The key figure](key-figure.png)" in md and "[05 · The ablation](notebooks/05_ablation.ipynb)" in md
    assert "jupyter lab notebooks/" in md


def _exercise_nb(answer: str, check: str, cell_ids=("a", "b", "c")) -> dict:
    meta = {"answer": {"nbgrader": {"grade_id": "ex01-1-answer", "solution": True, "grade": False}},
            "check": {"nbgrader": {"grade_id": "ex01-1-check", "solution": False, "grade": True, "points": 1}}}
    out = [{"output_type": "stream", "name": "stdout", "text": "printed\n"}]
    return {"cells": [
        {"id": cell_ids[0], "cell_type": "code", "metadata": {}, "source": "x = 1\nprint('lesson')",
         "outputs": [{"output_type": "stream", "name": "stdout", "text": "lesson\n"}], "execution_count": 1},
        {"id": cell_ids[1], "cell_type": "code", "metadata": meta["answer"], "source": answer, "outputs": out,
         "execution_count": 2},
        {"id": cell_ids[2], "cell_type": "code", "metadata": meta["check"], "source": check, "outputs": out,
         "execution_count": 3}], "metadata": {}, "nbformat": 4, "nbformat_minor": 5}


def test_the_student_view_keeps_lesson_outputs_only():
    lecturer = _exercise_nb("y = None\n### BEGIN SOLUTION\ny = secret_answer(2)\n### END SOLUTION",
                            "assert y\n### BEGIN HIDDEN TESTS\nassert y == hidden_value(2)\n### END HIDDEN TESTS")
    released = _exercise_nb("y = None\n# YOUR CODE HERE\nraise NotImplementedError()", "assert y\n")
    for c in released["cells"]:
        c["outputs"], c["execution_count"] = [], None
    view = book.student_view(lecturer, released)
    assert [len(c["outputs"]) for c in view["cells"]] == [1, 0, 0]  # the lesson's output; no exercise output
    assert view["cells"][0]["execution_count"] == 1 and view["cells"][1]["source"] == released["cells"][1]["source"]
    assert exercises.leaks(lecturer, view) == []
    changed = json.loads(json.dumps(released))
    changed["cells"][0]["source"] = "x = 2"  # a cell the release changed: its lecturer output is not shown
    assert book.student_view(lecturer, changed)["cells"][0]["outputs"] == []
    with pytest.raises(book.BookError, match="does not have the lecturer notebook's cells"):
        book.student_view(lecturer, _exercise_nb("", "", cell_ids=("a", "c", "b")))


# --------------------------------------------------------------------------- the student book holds no solution

PACKAGE_TEXT = "\n".join(p.read_text(encoding="utf-8") for p in sorted(book.PACKAGE_DIR.rglob("*.py")))


def secret_lines(nb: dict) -> list[str]:
    """What a student must not see of a lecturer notebook: the lines of its solutions and hidden tests, and
    what its exercise cells printed (the solution's results), where at least 16 characters long and shown
    nowhere else: not in a line of the notebook outside those regions, not in its other outputs, not in
    the package's source (the student edition ships the package)."""
    public, secret = set(), []
    shown = []
    for c in nb["cells"]:
        src = "".join(c.get("source", ""))
        solution, rest = exercises._split_solutions(src)
        visible = exercises.visible_check(src).splitlines()
        secret += solution + [ln for ln in rest if ln not in visible and ln.strip() not in exercises.HIDDEN_MARKERS]
        shown += visible
        printed = [ln for o in c.get("outputs", []) for ln in "".join(o.get("text", "")).splitlines()]
        (secret.extend if c.get("metadata", {}).get("nbgrader") else public.update)(ln.strip() for ln in printed)
    public.update(ln.strip() for ln in shown)
    text = "\n".join(shown) + PACKAGE_TEXT
    return sorted({ln.strip() for ln in secret if len(ln.strip()) >= 16 and ln.strip() not in public
                   and ln.strip() not in text})


def site_texts(out: Path) -> dict[str, str]:
    """Every text file of a built site as a reader gets it: a page's HTML and its text (tags dropped, entities
    read: highlighted code is one span per token), a notebook's JSON and its cells' sources and printed
    outputs, the scripts (the search index) as they are."""
    texts = {}
    for p in sorted(Path(out).rglob("*")):
        if not p.is_file() or p.suffix not in (".html", ".ipynb", ".js", ".json", ".css"):
            continue
        raw = p.read_text(encoding="utf-8", errors="replace")
        if p.suffix == ".html":
            raw += "\n" + html.unescape(re.sub(r"<[^>]+>", "", raw))
        elif p.suffix == ".ipynb":
            cells = json.loads(raw).get("cells", [])
            raw += "\n" + "\n".join("".join(c.get("source", "")) + "\n" + "\n".join(
                "".join(o.get("text", "")) for o in c.get("outputs", [])) for c in cells)
        texts[p.relative_to(out).as_posix()] = raw
    return texts


MARKER_LINE = re.compile(r"^\s*### (?:BEGIN|END) (?:SOLUTION|HIDDEN TESTS)\s*$", re.M)


def leaked(texts: dict[str, str], secrets: dict[str, list[str]],
           lessons: set[str] = frozenset()) -> list[tuple[str, str]]:
    """(file, what) for each solution marker and secret line found in the site's texts. A marker counts as a
    line of its own anywhere, and as any text in a lesson page or a notebook (the package's source, which
    defines them, and the docs, which name them, may hold them in a line of other text)."""
    found = []
    for rel, text in texts.items():
        markers = [m.group(0).strip() for m in MARKER_LINE.finditer(text)]
        if rel in lessons or rel.endswith(".ipynb"):
            markers += [m for m in (*exercises.SOLUTION_MARKERS, *exercises.HIDDEN_MARKERS) if m in text]
        found += [(rel, m) for m in markers]
        found += [(rel, line) for line in sorted({ln for lines in secrets.values() for ln in lines}) if line in text]
    return found  # a line secret in several notebooks (a hidden test's comment) is found once per file


@pytest.fixture(scope="module")
def student_book(tmp_path_factory):
    """The student edition of the book, built once from the committed lessons (no docs, two source pages)."""
    try:
        book.check_node()
        book.check_jupyter_book()
    except book.BookError as exc:
        if os.environ.get(REQUIRE_ENV, "") not in ("", "0"):
            pytest.fail(f"{REQUIRE_ENV}=1, but the student book cannot be built: {exc}")
        pytest.skip(f"student book: {exc}")
    out = tmp_path_factory.mktemp("student") / "site"
    with pytest.MonkeyPatch.context() as mp:
        _few_modules(mp)
        summary = book.build(out, docs=[], readme=None, katex=False, edition="student", log=lambda m: None)
    secrets = {nb.name: secret_lines(json.loads(nb.read_text(encoding="utf-8"))) for nb in book.lesson_notebooks()}
    return out, summary, secrets


def test_the_student_book_holds_no_solution(student_book):
    out, summary, secrets = student_book
    assert summary["edition"] == "student" and summary["figures"] > 0  # the lessons' figures are there
    n = sum(map(len, secrets.values()))
    assert n >= 100  # every lecturer notebook's solutions, hidden tests, printouts
    for doc in ("book.md", "teaching.md"):  # the number the docs state
        assert f"{n} lines of 16 characters" in " ".join((book.DOCS_DIR / doc).read_text(encoding="utf-8").split())
    assert all(secrets[nb.name] for nb in book.lesson_notebooks() if nb.name[:2] in exercises.EXERCISE_NOTEBOOKS)
    texts = site_texts(out)
    assert summary["downloads"] and all(rel in texts for rel in summary["downloads"].values())
    assert leaked(texts, secrets, set(summary["lesson_pages"].values())) == []
    released = json.loads((out / summary["downloads"]["05_ablation.ipynb"]).read_text(encoding="utf-8"))
    assert "raise NotImplementedError()" in "".join("".join(c["source"]) for c in released["cells"])
    assert not any(c.get("outputs") for c in released["cells"])  # the student notebook: outputs cleared
    for name, rel in summary["downloads"].items():  # each lesson links its notebook, saying which it is
        page = (out / summary["lesson_pages"][name]).read_text(encoding="utf-8")
        said = "the exercises to solve" if name[:2] in exercises.EXERCISE_NOTEBOOKS else "executed"
        assert f'href="{rel}" download' in page and said in page.split('class="download"')[1][:300], name


def test_the_leak_check_finds_a_planted_solution_line(student_book):
    """The planted defect: one line of a solution written into a lesson page (highlighted, as the book
    writes code) and into a downloadable notebook, and a marker into the search index."""
    out, summary, secrets = student_book
    texts = site_texts(out)
    line = secrets["05_ablation.ipynb"][0]
    page = summary["lesson_pages"]["05_ablation.ipynb"]
    planted = dict(texts)
    raw = (out / page).read_text(encoding="utf-8")
    code = "<pre><code>" + "\n".join(book.highlight_lines(line)) + "</code></pre>"
    planted[page] = raw + "\n" + html.unescape(re.sub(r"<[^>]+>", "", raw.replace("</main>", code + "</main>")))
    planted[page] += "\nx = 1  ### BEGIN SOLUTION"  # a marker in a line of code
    assert leaked(planted, secrets, {page}) == [(page, "### BEGIN SOLUTION"), (page, line)]
    nb_rel = summary["downloads"]["03_losses_explained.ipynb"]
    nb = json.loads((out / nb_rel).read_text(encoding="utf-8"))
    nb["cells"][-1]["source"] = "### BEGIN SOLUTION\n" + secrets["03_losses_explained.ipynb"][0]
    (Path(str(out) + "-planted") / "notebooks").mkdir(parents=True)
    (Path(str(out) + "-planted") / nb_rel).write_text(json.dumps(nb))
    found = leaked(site_texts(Path(str(out) + "-planted")), secrets)
    assert (nb_rel, "### BEGIN SOLUTION") in found and (nb_rel, secrets["03_losses_explained.ipynb"][0]) in found
    index = "_static/" + book.SEARCH_INDEX
    assert set(leaked({index: texts[index] + "### END HIDDEN TESTS"}, secrets)) == {(index, "### END HIDDEN TESTS")}


# --------------------------------------------------------------------------- the reader's features in a browser

def _search_word(lesson: str) -> str:
    """A word of the lesson's markdown that no other lesson's markdown holds (its most frequent one of 9+ letters)."""
    words = {}
    for nb in book.lesson_notebooks():
        md = " ".join("".join(c["source"]) for c in json.loads(nb.read_text(encoding="utf-8"))["cells"]
                      if c["cell_type"] == "markdown")
        words[nb.name] = re.findall(r"\b[a-z]{9,}\b", md.lower())
    others = {w for name, ws in words.items() if name != lesson for w in ws}
    ours = [w for w in words[lesson] if w not in others]
    return max(sorted(set(ours)), key=ours.count)


def _printed_tables(nb: Path) -> list[list[list[str]]]:
    """The pipe tables a notebook printed, read here on their own: runs of ``|`` lines whose second line is
    dashes and whose rows all have the header's cell count; cells without their ** and ` marks."""
    tables = []
    for c in json.loads(nb.read_text(encoding="utf-8"))["cells"]:
        for o in c.get("outputs", []):
            if o.get("name") == "stderr":
                continue
            text = "".join(o.get("text", "") or o.get("data", {}).get("text/plain", ""))
            for run in re.findall(r"(?m)(?:^\|.*\|$\n?)+", text):
                rows = [[x.strip().replace("**", "").replace("`", "") for x in ln.strip()[1:-1].split("|")]
                        for ln in run.strip().split("\n")]
                if (len(rows) >= 2 and all(re.fullmatch(r":?-+:?", x) for x in rows[1])
                        and all(len(r) == len(rows[0]) for r in rows)):
                    tables.append([rows[0], *rows[2:]])
    return tables


NARROW = """() => {
  const side = document.querySelector('nav.sidebar'), button = document.querySelector('.menu-toggle');
  const title = document.querySelector('.topbar-title'), main = document.querySelector('main');
  const visible = e => !!e && getComputedStyle(e).display !== 'none' && e.getBoundingClientRect().width > 0;
  const wide = [...document.querySelectorAll('main pre, main .printed-table, main .math-display')]
    .filter(e => e.scrollWidth > e.clientWidth + 1);
  return {sidebar: visible(side), button: visible(button),
          overflow: document.documentElement.scrollWidth - window.innerWidth,
          body_overflow: document.body.scrollWidth - window.innerWidth,
          title_lines: title ? Math.round(title.getBoundingClientRect().height /
                                          parseFloat(getComputedStyle(title).lineHeight)) : 0,
          main_width: main.getBoundingClientRect().width, width: window.innerWidth,
          scrollers: wide.length,
          cut: wide.filter(e => !['auto', 'scroll'].includes(getComputedStyle(e).overflowX)
                                 || e.getBoundingClientRect().right > window.innerWidth + 1).length};
}"""


def _narrow_problems(seen: dict) -> list[str]:
    """What is wrong with a page at 420 px, as NARROW saw it."""
    problems = []
    if seen["sidebar"] or not seen["button"]:
        problems.append(f"the sidebar shows ({seen['sidebar']}) or the menu button does not ({seen['button']})")
    if seen["overflow"] > 0 or seen["body_overflow"] > 0:
        problems.append(f"the page is {seen['overflow']} px wider than the screen")
    if seen["title_lines"] != 1 or seen["main_width"] < 0.9 * seen["width"]:
        problems.append(f"the title takes {seen['title_lines']} lines, the text {seen['main_width']:.0f} px")
    if seen["cut"]:
        problems.append(f"{seen['cut']} long code or output blocks are cut off instead of scrolling")
    return problems


def _table_cells(page, k: int) -> list[list[str]]:
    return page.evaluate("k => [...document.querySelectorAll('main .printed-table table')[k].rows]"
                         ".map(r => [...r.cells].map(c => c.innerText.trim()))", k)


def _search(page, word: str) -> list[str]:
    page.fill("#search-input", word)
    page.wait_for_function("() => document.querySelectorAll('#search-results li').length > 0", timeout=10_000)
    return page.evaluate("() => [...document.querySelectorAll('#search-results a')].map(a => a.href)")


@pytest.fixture(scope="module")
def reader(served_book):
    """The built book read as a reader does: searched, its notebooks downloaded, its printed tables read, and
    every lesson at 420 px wide; each check also run once on a page with a defect planted in the browser."""
    from playwright.sync_api import sync_playwright

    out, base, summary = served_book
    lessons = summary["lesson_pages"]
    seen: dict = {"narrow": {}, "tables": {}, "downloads": {}}
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        word = seen["word"] = _search_word("03_losses_explained.ipynb")
        page.goto(f"{base}/index.html")
        seen["hits"] = _search(page, word)
        target = next((h for h in seen["hits"] if h.split("#")[0].endswith("/" + lessons["03_losses_explained.ipynb"])),
                      None)
        if target:
            page.locator(f'#search-results a[href="{target[len(base) + 1:]}"]').first.click()
            page.wait_for_load_state("load")
            seen["landed"] = (page.url.split("#")[0], word in page.locator("main").inner_text().lower())
        page.route("**/" + book.SEARCH_INDEX, lambda route: route.fulfill(
            body="window.geodepthSearchIndex = {\"pages\": []};", content_type="text/javascript"))
        page.goto(f"{base}/index.html")  # planted: an index without the lessons
        seen["hits_planted"] = _search(page, word)
        page.unroute("**/" + book.SEARCH_INDEX)
        page.goto((out / "index.html").as_uri())  # opened from disk: no server
        seen["hits_file"] = _search(page, word)
        narrow = browser.new_page(viewport={"width": 420, "height": 800})  # each lesson, as on a phone
        for name, rel in [("", "index.html"), *lessons.items()]:
            narrow.goto(f"{base}/{rel}")
            seen["narrow"][rel] = narrow.evaluate(NARROW)
            n = 0
            if name:
                seen["downloads"][name] = narrow.evaluate(
                    "() => [...document.querySelectorAll('main a[download]')].map(a => a.getAttribute('href'))")
                n = narrow.locator("main .printed-table table").count()
                seen["tables"][name] = [_table_cells(narrow, k) for k in range(n)]
            if name and "moved" not in seen:  # planted: the download link pointing at a file the site lacks
                narrow.evaluate("() => document.querySelector('main a[download]').setAttribute('href', "
                                "'notebooks/missing.ipynb')")
                seen["moved"] = (name, narrow.evaluate(
                    "() => [...document.querySelectorAll('main a[download]')].map(a => a.getAttribute('href'))"))
            if n and "swapped" not in seen:  # planted: two cells of the first printed table swapped
                narrow.evaluate("() => { const r = document.querySelector('main .printed-table table').rows[1];"
                                " r.insertBefore(r.cells[1], r.cells[0]); }")
                seen["swapped"] = (name, _table_cells(narrow, 0))
        narrow.click(".menu-toggle")
        seen["opened"] = narrow.evaluate(NARROW)
        narrow.click(".menu-toggle")
        narrow.add_style_tag(content="nav.sidebar { display: block !important; } main pre { overflow-x: visible "
                             "!important; max-width: none !important; }")  # planted: the wide-screen layout
        seen["narrow_planted"] = narrow.evaluate(NARROW)
        browser.close()
    return out, summary, seen


def test_search_finds_a_word_of_a_lesson_and_opens_its_page(reader):
    out, summary, seen = reader
    page = summary["lesson_pages"]["03_losses_explained.ipynb"]
    assert any(h.split("#")[0].endswith("/" + page) for h in seen["hits"]), (seen["word"], seen["hits"][:5])
    assert seen["landed"][0].endswith("/" + page) and seen["landed"][1], seen["landed"]
    index = book.book_reader.read_search_index((out / "_static" / book.SEARCH_INDEX).read_text(encoding="utf-8"))
    assert {p["u"] for p in index["pages"]} >= set(summary["pages"])  # every page is searched
    assert seen["hits_planted"] == [], seen["hits_planted"]  # planted: an index without the lesson finds nothing
    assert any(h.startswith("file://") and h.split("#")[0].endswith("/" + page) for h in seen["hits_file"])


def _download_problems(out: Path, name: str, hrefs: list[str]) -> list[str]:
    """What is wrong with a lesson's download links: not one link, or its file missing or not the notebook."""
    if len(hrefs) != 1:
        return [f"{name}: {len(hrefs)} download links"]
    target = out / hrefs[0]
    if not target.is_file() or target.read_bytes() != (exercises.NOTEBOOK_DIR / name).read_bytes():
        return [f"{name}: {hrefs[0]} is not the executed notebook"]
    return []


def test_each_lesson_links_its_notebook_and_the_file_is_there(reader):
    out, summary, seen = reader
    assert set(seen["downloads"]) == set(summary["notebooks"])
    assert not [p for name, hrefs in seen["downloads"].items() for p in _download_problems(out, name, hrefs)]
    assert all(hrefs == [f"notebooks/{name}"] for name, hrefs in seen["downloads"].items())
    assert _download_problems(out, *seen["moved"])  # planted: a link to a file the site does not hold


def test_printed_pipe_tables_are_tables(reader):
    out, summary, seen = reader
    counts = {}
    for name in summary["notebooks"]:
        expected = _printed_tables(exercises.NOTEBOOK_DIR / name)
        counts[name[:2]] = len(expected)
        assert seen["tables"][name] == expected, name  # every cell, in order
    assert counts["04"] == 6 and counts["05"] >= 6 and counts["06"] == 6, counts
    name, swapped = seen["swapped"]  # planted: the same cells, two of them swapped, are seen as wrong
    first = seen["tables"][name][0]
    assert swapped != first and sorted(map(sorted, swapped)) == sorted(map(sorted, first))


def test_a_narrow_screen_hides_the_sidebar_behind_a_button(reader):
    _, _, seen = reader
    bad = {rel: _narrow_problems(s) for rel, s in seen["narrow"].items() if _narrow_problems(s)}
    assert not bad
    assert sum(s["scrollers"] for s in seen["narrow"].values()) > 0  # long code lines do scroll, visibly
    assert seen["opened"]["sidebar"] and seen["opened"]["overflow"] <= 0  # the button opens it
    planted = _narrow_problems(seen["narrow_planted"])  # planted: the wide layout at 420 px
    assert len(planted) >= 2 and "sidebar" in planted[0], planted


def test_the_landing_page_is_the_books_own(served_book):
    """The landing page: the README's purpose, its key figure (the same PNG as notebook 05 stores), every
    lesson linked in order, the commands to run them; the README is a page of its own."""
    out, _, summary = served_book
    page = (out / "index.html").read_text(encoding="utf-8")
    text = html.unescape(re.sub(r"<[^>]+>", "", page))
    readme = book.README.read_text(encoding="utf-8")
    assert summary["key_figure"] and " ".join(book.book_reader.readme_purpose(readme)[0].split())[:40] in " ".join(
        text.split()).replace("\u201c", '"').replace("\u201d", '"').replace("**", "")
    name, section, _ = book.book_reader.key_figure_ref(readme)
    png = book.book_reader.section_figure(json.loads((exercises.NOTEBOOK_DIR / name).read_text(encoding="utf-8")),
                                          section)
    shown = [out / src for src in re.findall(r'<img src="([^"]+)"', page)]
    assert [p.read_bytes() for p in shown] == [png]
    other = book.book_reader.section_figure(json.loads((exercises.NOTEBOOK_DIR / name).read_text(encoding="utf-8")),
                                            "The second study: the paper's losses switched on")  # a wrong figure
    assert other is not None and [p.read_bytes() for p in shown] != [other]
    links = re.findall(r'<li>(?:<p>)?<a href="([\w.-]+\.html)">', page.split('id="the-lessons"')[1].split("</ol>")[0])
    assert links == list(summary["lesson_pages"].values())  # every lesson, in order
    assert "jupyter lab notebooks/" in text and "build the book" not in text.lower()
    assert "readme.html" in summary["pages"]


def test_cells_tagged_remove_cell_are_left_out_of_the_lesson_pages(served_book):
    """The lessons' "record" cells (which save the numbers tests/test_results.py checks) carry the
    ``remove-cell`` tag: the longest line of each is on no HTML page of the book, while the longest line
    of the code cell before it is, so the check reads text from where those cells would be."""
    out, _, _ = served_book
    pages = [text for rel, text in site_texts(out).items() if rel.endswith(".html")]
    seen = 0
    for nb_path in book.lesson_notebooks():
        cells = json.loads(nb_path.read_text(encoding="utf-8"))["cells"]
        for i, cell in enumerate(cells):
            if "remove-cell" not in cell["metadata"].get("tags", []):
                continue
            gone = max("".join(cell["source"]).splitlines(), key=len).strip()
            kept = next(max("".join(c["source"]).splitlines(), key=len).strip() for c in cells[i - 1::-1]
                        if c["cell_type"] == "code" and "remove-cell" not in c["metadata"].get("tags", []))
            assert not any(gone in text for text in pages), f"{nb_path.name}: {gone!r} is shown"
            assert any(kept in text for text in pages), f"{nb_path.name}: {kept!r} is not found"
            seen += 1
    assert seen == 7
