"""``python -m geodepth_lite book --out DIR``: the executed notebooks as a static web book.

The book is read in a browser like d2l or the UvA tutorials: a landing page (the project's purpose,
the README's key figure, the lessons, how to run them), the eight lessons (notebooks 00-07, with the
outputs they were committed with, nothing re-executed, each with its notebook to download), the
README and the reference docs, and one page of source per package module; a search over every page,
an "on this page" list, printed Markdown tables drawn as tables (:mod:`geodepth_lite.workbook.book_reader`).
``--edition student`` leaves out every solution, exercise output and hidden test
(:func:`student_notebooks`): the book to publish to a class. The route, in three steps:

1. **Jupyter Book 2 (MyST) parses the sources.** The notebooks, the README and docs/ are staged in
   a temporary project and ``jupyter-book build --site`` turns them into MyST's page content: one
   JSON file per page (the mdast tree), with the math already typeset by KaTeX, cross-references and
   links between the pages resolved, and the figures written out as files.
2. **This module renders that content to HTML.** Jupyter Book's own web theme is not on a package
   registry (mystmd downloads it from its template service when the site is built), so a book
   built offline cannot use it. The staged project names a local site template (a stub) instead,
   and the pages are rendered here: headings, paragraphs, lists, tables, code with highlighting,
   outputs with their figures, math, links. Each solution of a graded exercise (the lines between
   ``### BEGIN SOLUTION`` and ``### END SOLUTION``, and the outputs of its cell) and each block of
   hidden tests folds away behind a "Show solution" control (an HTML ``<details>`` element, so no
   script is needed). Every name of the package a lesson uses (``losses.sdf_loss`` in a code cell
   or in inline code) links to the line that defines it on the module's source page, and each
   source page lists the lessons that use its functions.
3. **KaTeX's style sheet and fonts** come from the npm registry (``npm pack katex@<version>``,
   the version mystmd typesets with, checked against the pinned hash), kept in the workspace's
   data folder after the first build. Where npm cannot fetch it, the equations are shown with the
   browser's own MathML renderer (KaTeX writes both) and the command says so.

The site needs no network and no server of its own: any static file server (``python -m
http.server``) serves it. Jupyter Book 2 runs on Node.js 18 or newer; without it the command
stops with one line saying so.
"""

from __future__ import annotations

import argparse
import ast
import base64
import contextlib
import functools
import hashlib
import html
import html.parser
import importlib.util
import json
import os
import re
import shutil
import stat
import subprocess
import sys
import tarfile
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from pygments.formatters import HtmlFormatter
from pygments.lexers import get_lexer_by_name
from pygments.token import STANDARD_TYPES, Name, Operator, Text
from pygments.util import ClassNotFound

from geodepth_lite import utils
from geodepth_lite.core.errors import UserError
from geodepth_lite.data import bounds
from geodepth_lite.views import recon
from geodepth_lite.workbook import book_reader, course, exercises
from geodepth_lite.workbook.exercises import HIDDEN_MARKERS, NOTEBOOK_DIR, SOLUTION_MARKERS, git_tracked

ROOT = utils.package_parent()
PACKAGE_DIR = ROOT / "geodepth_lite"
DOCS_DIR = ROOT / "docs"
README = ROOT / "README.md"
MARKER = ".geodepth-book.json"  # the output folder's marker: whether complete, and the files it wrote (SHA-256)
NEW_DIR = ".geodepth-book-new"  # + "-<pid>": the site being built, inside the output folder until it is complete
STAGING = re.compile(r"^\.geodepth-book-new-(\d+)$")
TEMP_STAGING = re.compile(r"^geodepth-(?:book|katex)-(\d+)-[A-Za-z0-9_]+$")  # MyST projects in the temp folder
# the names it writes: pages, source pages, the lessons' notebooks to download, style sheets, scripts and figures
BOOK_PATH = re.compile(r"^(?:[\w.-]+\.html|\.nojekyll|source/[\w.-]+\.html|notebooks/[\w.-]+\.ipynb"
                       r"|_static(?:/[\w.-]+)+)$")
WRITTEN_BY = "python -m geodepth_lite book"
NODE_MIN = 18  # Jupyter Book 2 runs on Node.js 18 or newer
KATEX_VERSION = "0.15.6"  # the KaTeX that jupyter-book 2.1.7 (mystmd 1.11) typesets with
KATEX_INTEGRITY = ("sha512-UpzJy4yrnqnhXvRPhjEuLA4lcPn6eRngixW7Q3TJErjg3Aw2PuLFBzTkdUb89UtumxjhHTqL3a5GDGETMSwgJA==")
KATEX_MAX_BYTES = 8 * 2**20  # the npm tarball is about 1.3 MB; a larger file is refused
SOLUTION_TAG = "geodepth-solution"  # the tag a staged notebook's solution cells carry through MyST
BUILD_TIMEOUT_S = 900
MAX_PAGE_JSON_BYTES = 64 * 2**20
STATIC = "_static"
INLINE_TAGS = {"strong": "strong", "emphasis": "em", "underline": "u", "delete": "del", "superscript": "sup",
               "subscript": "sub", "span": "span"}  # MyST node type -> HTML element
PLOTLY_JS = "plotly.min.js"  # drawn by the 3D views (notebook 07), from the plotly package
BOOK_JS_FILE = "book.js"  # the sidebar's button on a narrow screen, the search
SEARCH_INDEX = "search-index.js"  # the search index, loaded when the search box is first used
EDITIONS = ("lecturer", "student")
SOURCE = "source"

CSS = """
:root { --fg: #1d2330; --muted: #5b6474; --line: #d9dee7; --accent: #1f5fa8; --code: #f6f8fa; }
* { box-sizing: border-box; }
body { margin: 0; color: var(--fg); font: 16px/1.6 system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; }
a { color: var(--accent); }
.layout { display: flex; min-height: 100vh; }
nav.sidebar { width: 280px; flex: none; border-right: 1px solid var(--line); padding: 1rem; font-size: 14px;
  position: sticky; top: 0; height: 100vh; overflow-y: auto; background: #fbfcfd; }
nav.sidebar .book-title { font-weight: 700; font-size: 16px; display: block; margin-bottom: .75rem; }
nav.sidebar .book-title small { display: block; font-weight: 400; font-size: 13px; color: var(--muted); }
nav.sidebar ul { list-style: none; padding-left: 0; margin: 0 0 .5rem 0; }
nav.sidebar li { margin: .15rem 0; }
nav.sidebar li.group { margin-top: .8rem; font-weight: 600; color: var(--muted); text-transform: uppercase;
  font-size: 12px; letter-spacing: .04em; }
nav.sidebar li.current > a { font-weight: 700; }
nav.sidebar a { text-decoration: none; }
main { flex: 1; min-width: 0; max-width: 980px; padding: 1.5rem 2.5rem 4rem; }
pre { background: var(--code); padding: .6rem .8rem; overflow-x: auto; border-radius: 4px; font-size: 13.5px;
  line-height: 1.45; margin: .4rem 0; }
code { font-family: ui-monospace, SFMono-Regular, Menlo, Consolas, monospace; font-size: .9em; }
p code, li code, td code { background: var(--code); padding: .05rem .25rem; border-radius: 3px; }
a.src code { text-decoration: underline dotted; }
pre a.src { color: inherit; text-decoration: underline dotted var(--accent); }
table { border-collapse: collapse; margin: .8rem 0; display: block; overflow-x: auto; }
th, td { border: 1px solid var(--line); padding: .25rem .55rem; text-align: left; vertical-align: top; }
th { background: #f1f4f8; }
img { max-width: 100%; height: auto; }
.cell { margin: 1rem 0; }
.cell-input pre { border-left: 3px solid var(--accent); }
.cell-outputs { margin-left: .8rem; }
.cell-outputs pre { background: #fff; border: 1px solid var(--line); }
.cell-outputs pre.stderr { background: #fff5f5; }
.math-display { overflow-x: auto; margin: .8rem 0; }
.math-display .eq-number { float: right; color: var(--muted); }
details.solution, details.hidden-tests { border: 1px solid #c8d6e8; border-radius: 4px; margin: .4rem 0;
  padding: .2rem .6rem; background: #f7faff; }
details.solution > summary, details.hidden-tests > summary { cursor: pointer; color: var(--accent);
  font-weight: 600; font-size: 14px; }
.admonition { border-left: 4px solid var(--accent); background: #f4f8fd; padding: .4rem .9rem; margin: 1rem 0; }
.admonition-title { font-weight: 700; }
.pager { display: flex; justify-content: space-between; margin-top: 3rem; border-top: 1px solid var(--line);
  padding-top: 1rem; gap: 1rem; }
.used-functions { margin-top: 2.5rem; border-top: 1px solid var(--line); font-size: 14px; }
.repo-file { font-style: italic; }
.source-code { counter-reset: none; }
.source-code .ln { display: inline-block; width: 4.5em; color: #9aa3b2; text-align: right; padding-right: 1em;
  user-select: none; text-decoration: none; }
.source-code .line:target { background: #fff4c2; }
.source-code .line { display: block; }
main { overflow-wrap: break-word; }
pre, .math-display, .printed-table { max-width: 100%; overflow-x: auto; }
pre { white-space: pre; scrollbar-width: thin; }
.printed-table table { font-size: 13.5px; margin: .4rem 0; }
.printed-table td, .printed-table th { white-space: nowrap; }
.download { font-size: 14px; margin: -.4rem 0 .8rem; }
.page-toc { border: 1px solid var(--line); border-radius: 4px; padding: .3rem .9rem; margin: .6rem 0 1.2rem;
  font-size: 14px; background: #fbfcfd; }
.page-toc-title { font-weight: 600; margin: .2rem 0; }
.page-toc ul { list-style: none; padding-left: 0; margin: 0 0 .3rem; }
.page-toc li.d3 { padding-left: 1.1rem; }
form.search input { width: 100%; font: inherit; font-size: 14px; padding: .3rem .5rem; border: 1px solid var(--line);
  border-radius: 4px; margin-bottom: .4rem; }
.search-results { max-height: 55vh; overflow-y: auto; }
.search-results li { margin: .35rem 0; }
.search-results .snippet { display: block; color: var(--muted); font-size: 12.5px; line-height: 1.35; }
.topbar { display: none; }
@media (min-width: 1580px) {
  main { margin-right: 270px; }
  .page-toc { position: fixed; right: 1rem; top: 1.5rem; width: 250px; max-height: calc(100vh - 3rem);
    overflow-y: auto; margin: 0; }
}
@media (max-width: 900px) {
  .layout { display: block; }
  .topbar { display: flex; align-items: center; gap: .7rem; position: sticky; top: 0; z-index: 20;
    background: #fff; border-bottom: 1px solid var(--line); padding: .45rem .9rem; }
  .topbar-title { font-weight: 700; white-space: nowrap; overflow: hidden; text-overflow: ellipsis; min-width: 0;
    text-decoration: none; }
  .menu-toggle { flex: none; font: inherit; font-size: 14px; padding: .25rem .65rem; border: 1px solid var(--line);
    border-radius: 4px; background: #fbfcfd; color: var(--fg); cursor: pointer; }
  nav.sidebar { display: none; }
  body.nav-open nav.sidebar { display: block; position: fixed; top: 2.8rem; left: 0; bottom: 0; height: auto;
    width: min(320px, 88vw); z-index: 15; box-shadow: 0 0 18px rgba(0, 0, 0, .18); }
  main { max-width: none; padding: 1rem 1rem 3rem; }
  main h1 { font-size: 1.55rem; line-height: 1.25; }
  .pager { flex-wrap: wrap; }
}
"""
# where KaTeX's style sheet is missing: hide KaTeX's HTML rendering, show its MathML one
MATHML_CSS = """
.katex-html { display: none; }
.katex .katex-mathml { position: static !important; clip: auto !important; width: auto !important;
  height: auto !important; overflow: visible !important; padding: 0 !important; border: 0 !important; }
.katex-display > .katex { display: block; text-align: center; }
"""


class BookError(UserError):
    """A failure of the book build; printed as one line ``error: ...`` with exit status 2."""


# --------------------------------------------------------------------------- Node.js and jupyter-book


def node_version(node: str) -> tuple[int, ...] | None:
    """``node --version`` as numbers (``(20, 20, 2)``), or None where it does not answer."""
    try:
        done = subprocess.run([node, "--version"], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    m = re.match(r"^v?(\d+)\.(\d+)\.(\d+)", done.stdout.strip())
    return tuple(int(g) for g in m.groups()) if done.returncode == 0 and m else None


def check_node(path: str | None = None) -> str:
    """The ``node`` that Jupyter Book 2 will run on (found on ``path``, default PATH); a
    :class:`BookError` of one line where there is none, or it is older than Node.js 18."""
    node = shutil.which("node", path=path)
    if node is None:
        raise BookError(f"cannot build the book: Jupyter Book 2 needs Node.js {NODE_MIN} or newer, and no node "
                        "is on PATH; install Node.js (e.g. apt-get install nodejs) and run the command again")
    version = node_version(node)
    if version is None or version[0] < NODE_MIN:
        found = "an unreadable version" if version is None else "v" + ".".join(map(str, version))
        raise BookError(f"cannot build the book with {node}: Jupyter Book 2 needs Node.js {NODE_MIN} or newer, "
                        f"this one is {found}; install a newer Node.js and run the command again")
    return node


def check_jupyter_book() -> None:
    if importlib.util.find_spec("jupyter_book") is None:
        raise BookError("cannot build the book: the Python package jupyter-book is not installed; install "
                        "the project's environment (python -m pip install -r environment.txt)")


# --------------------------------------------------------------------------- the output folder


def _reserved(name: str) -> bool:
    """The names of the output folder that are the command's own: its marker, lock and staging folders."""
    return name in (MARKER, utils.LOCK_NAME) or STAGING.match(name) is not None


def check_out(out: Path) -> None:
    """Refuse an output folder the book must not write into: a file, a folder holding files git tracks,
    or a folder that is not empty and was not written by this command (no marker). A folder with a
    marker is checked file by file when the new site is ready (:func:`_publish`)."""
    out = Path(out)
    if os.path.lexists(out) and not out.is_dir():
        raise utils.FileProblem(f"cannot write the book into {out}: a file of that name exists; choose a "
                                "new or empty folder", out)
    if not out.is_dir():
        return
    tracked = git_tracked(out)
    if tracked:
        raise utils.FileProblem(f"cannot write the book into {out}: it holds {len(tracked)} file(s) of the "
                                f"checkout tracked by git (first {tracked[0]}); choose a new or empty folder", out)
    present = sorted(p.name for p in out.iterdir() if not _reserved(p.name))
    if present and not os.path.lexists(out / MARKER):
        raise utils.FileProblem(f"cannot write the book into {out}: the folder holds files the book command "
                                f"did not write (first {present[0]}); choose a new or empty folder", out)


def read_marker(out: Path) -> dict | None:
    """The output folder's marker (``{"complete": bool, "files": {path: sha256}, ...}``), or None where
    there is none (or it is not a regular file of at most 1 MB holding a JSON object)."""
    path = Path(out) / MARKER
    try:
        if not stat.S_ISREG(path.lstat().st_mode) or path.stat().st_size > 2**20:
            return None
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def regular_file_sha256(path: Path) -> str | None:
    """The SHA-256 of ``path`` where it is a regular file (a link is not followed); None otherwise."""
    try:
        if not stat.S_ISREG(path.lstat().st_mode):
            return None
        digest = hashlib.sha256()
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(2**20), b""):
                digest.update(chunk)
    except OSError:
        return None
    return digest.hexdigest()


def _in_folder(out: Path, rel: str) -> Path | None:
    """``out / rel`` for a path the book writes (:data:`BOOK_PATH`) whose folders on the way are real
    folders (no link) or missing; None otherwise."""
    parts = rel.split("/") if isinstance(rel, str) else []
    if not BOOK_PATH.match(rel or "") or any(p in ("", ".", "..") for p in parts):
        return None
    folder = Path(out)
    for part in parts[:-1]:
        folder = folder / part
        if os.path.lexists(folder) and (folder.is_symlink() or not folder.is_dir()):
            return None
    return Path(out, *parts)


def owned_files(out: Path, marker: dict | None) -> dict[str, str]:
    """The files in ``out`` the book wrote: recorded in its marker (``files``, or ``previous`` while a
    new site replaces an old one) and holding now exactly what was recorded. A file the marker does not
    name, one changed since, one of a name the book never writes, and anything a forged marker names
    otherwise are not the book's."""
    recorded: dict[str, set[str]] = {}
    for key in ("previous", "files"):
        files = (marker or {}).get(key)
        for rel, digest in files.items() if isinstance(files, dict) else ():
            if isinstance(digest, str) and re.fullmatch(r"[0-9a-f]{64}", digest):
                recorded.setdefault(rel, set()).add(digest)
    owned = {}
    for rel, digests in recorded.items():
        path = _in_folder(out, rel)
        digest = regular_file_sha256(path) if path is not None else None
        if digest in digests:
            owned[rel] = digest
    return owned


def _remove_owned(out: Path, rel: str, digest: str) -> None:
    """Delete ``out/rel`` if it still holds ``digest``, then the folders on its way that it left empty."""
    path = _in_folder(out, rel)
    if path is None or regular_file_sha256(path) != digest:
        return
    path.unlink()
    for folder in path.parents:
        if folder == Path(out) or Path(out) not in folder.parents:
            break
        try:
            folder.rmdir()
        except OSError:  # not empty: holds someone's files
            break


def _check_free(out: Path, new_files: dict[str, str], owned: dict[str, str]) -> None:
    """Refuse, before anything is changed, a new site that would overwrite a file (or a folder) the
    book did not write."""
    for rel in sorted(new_files):
        parts = rel.split("/")
        for k in range(1, len(parts) + 1):
            sub, path = "/".join(parts[:k]), Path(out, *parts[:k])
            if not os.path.lexists(path) or sub in owned:
                break
            if k < len(parts) and path.is_dir() and not path.is_symlink():
                continue
            raise utils.FileProblem(f"cannot write the book into {out}: {path} is in the way, and the book "
                                    "command did not write it (or it was changed since); move it away, or choose "
                                    "a new or empty folder", path)


def _plan(out: Path, new: Path) -> tuple[dict[str, str], dict[str, str]]:
    """(the files of the old site the book wrote, the files of the new site), each path -> SHA-256; a
    :class:`utils.FileProblem` where a new file would overwrite one the book did not write."""
    owned = owned_files(out, read_marker(out))
    new_files = {p.relative_to(new).as_posix(): regular_file_sha256(p) for p in sorted(new.rglob("*")) if p.is_file()}
    odd = [rel for rel in new_files if not BOOK_PATH.match(rel)]
    if odd:  # a rebuild would not know it as the book's own: never publish it
        raise BookError(f"cannot publish the book: it wrote {odd[0]}, a name outside the site's layout")
    _check_free(out, new_files, owned)
    return owned, new_files


def _publish(out: Path, new: Path, owned: dict[str, str], new_files: dict[str, str], summary: dict) -> None:
    """Replace the site in ``out`` with the complete one in ``new`` (a folder inside ``out``), file by file.

    Only files the book wrote are removed or replaced (``owned``, from :func:`_plan`); any other file
    stays. The marker says "incomplete", and names the old files and the new ones, from before the
    first old file goes until after the last new one is in, so that a site cut off half way is never
    taken as complete and its files are still known to be the book's."""
    utils.write_json_atomic(out / MARKER, {"complete": False, "written_by": WRITTEN_BY, "files": new_files,
                                           "previous": owned})
    for rel in sorted(set(owned) - set(new_files)):
        _remove_owned(out, rel, owned[rel])
    for rel in sorted(new_files):
        target = Path(out, *rel.split("/"))
        utils.make_dir(target.parent)  # an old file of the book's in the way is gone already
        with _writing(target):
            os.replace(new / rel, target)
    shutil.rmtree(new)  # only its emptied folders are left
    utils.write_json_atomic(out / MARKER, {"complete": True, "written_by": WRITTEN_BY, "files": new_files,
                                           **summary})


def _clear_site(out: Path) -> None:
    """After a failed publish: remove the book's files (old and new, as the marker names them), every
    other file left as it is; then the marker says incomplete and names no file."""
    for rel, digest in owned_files(out, read_marker(out)).items():
        with contextlib.suppress(OSError):
            _remove_owned(out, rel, digest)
    utils.write_json_atomic(out / MARKER, {"complete": False, "written_by": WRITTEN_BY, "files": {}})


@contextlib.contextmanager
def _writing(path: Path):
    """Any OSError of the block (a full disk: ``[Errno 28]`` names no file) as a FileProblem naming ``path``."""
    try:
        yield
    except utils.FileProblem:
        raise
    except OSError as exc:
        raise utils.FileProblem(f"cannot write {path}: {utils.os_reason(exc)}", path) from exc


def write_file(path: Path, data: str | bytes) -> None:
    """Write ``data`` (text as UTF-8) to ``path``; a failure names the file."""
    with _writing(path):
        Path(path).write_bytes(data.encode("utf-8") if isinstance(data, str) else data)


def copy_file(src: Path, dst: Path) -> None:
    """Copy ``src`` to ``dst``; a failure names both files."""
    try:
        shutil.copyfile(src, dst)
    except OSError as exc:
        raise utils.FileProblem(f"cannot copy {src} to {dst}: {utils.os_reason(exc)}", dst) from exc


def remove_stale_staging(folder: Path, pattern: re.Pattern = TEMP_STAGING) -> list[Path]:
    """Remove the staging folders in ``folder`` (named ``...-<pid>-...`` by ``pattern``) that a book
    command killed before it could clean up left behind: those of this user whose process is gone."""
    removed = []
    try:
        entries = sorted(Path(folder).iterdir())
    except OSError:
        return removed
    for entry in entries:
        m = pattern.match(entry.name)
        if m is None or int(m.group(1)) == os.getpid() or utils.pid_alive(int(m.group(1))):
            continue
        try:
            st = entry.lstat()
        except OSError:
            continue
        if stat.S_ISDIR(st.st_mode) and st.st_uid == getattr(os, "getuid", lambda: st.st_uid)():
            shutil.rmtree(entry, ignore_errors=True)
            removed.append(entry)
    return removed


# --------------------------------------------------------------------------- staging the MyST project


def lesson_notebooks(folder: Path = NOTEBOOK_DIR) -> list[Path]:
    """The numbered notebooks 00-07 (``NN_name.ipynb``), in order."""
    return sorted(p for p in Path(folder).glob("[0-9][0-9]_*.ipynb") if p.name[:2] <= "07")


def tag_solutions(nb: dict) -> dict:
    """The notebook with :data:`SOLUTION_TAG` added to each nbgrader solution cell (MyST keeps a cell's
    tags in its page content but not its nbgrader metadata)."""
    for cell in nb.get("cells", []):
        meta = cell.setdefault("metadata", {})
        if meta.get("nbgrader", {}).get("solution"):
            tags = meta.setdefault("tags", [])
            if SOLUTION_TAG not in tags:
                tags.append(SOLUTION_TAG)
    return nb


KEY_FIGURE_FILE = "key-figure.png"  # the landing page's figure, as staged in the MyST project


def stage(project: Path, notebooks: list[Path], docs: list[Path], readme: Path | None, landing: str | None = None,
          figure: bytes | None = None) -> None:
    """Write the MyST project to build into ``project``: index.md (the landing page, ``landing``; the README
    where none is given), its key figure, notebooks/ (tagged copies), the README and docs/ as reference
    pages, myst.yml with the table of contents, and the local site template."""
    for folder in ("notebooks", "docs", "_template"):
        utils.make_dir(project / folder)
    if landing is not None:
        write_file(project / "index.md", landing)
        if figure is not None:
            write_file(project / KEY_FIGURE_FILE, figure)
    elif readme is not None:
        copy_file(readme, project / "index.md")
    else:
        write_file(project / "index.md", "# geodepth-lite\n\nThe lessons of the workbook, in order.\n")
    lines = ["version: 1", "project:", "  title: geodepth-lite", "  toc:", "    - file: index.md"]
    if notebooks:
        lines += ["    - title: Lessons", "      children:"]
    for nb in notebooks:
        try:
            data = json.loads(nb.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise BookError(f"cannot read {nb}: {exc}") from None
        write_file(project / "notebooks" / nb.name, json.dumps(tag_solutions(data), indent=1, ensure_ascii=False))
        lines.append(f"        - file: notebooks/{nb.name}")
    readme_page = landing is not None and readme is not None
    if docs or readme_page:
        lines += ["    - title: Reference", "      children:"]
    if readme_page:  # beside the landing page, the README is a reference page (its links resolve from the top)
        text = readme.read_text(encoding="utf-8")
        write_file(project / "README.md", "---\ntitle: The README\n---\n\n" + text)
        lines.append("        - file: README.md")
    for doc in docs:
        copy_file(doc, project / "docs" / doc.name)
        lines.append(f"        - file: docs/{doc.name}")
    lines += ["site:", "  title: geodepth-lite", "  template: ./_template", ""]
    write_file(project / "myst.yml", "\n".join(lines))
    # a local site template: MyST takes its options from it instead of asking its template service
    write_file(project / "_template" / "template.yml",
        "myst: v1\nkind: site\ntitle: geodepth-lite static book (rendered by geodepth_lite.workbook.book)\n")


def landing_page(readme: Path | None, notebooks: list[Path], edition: str, log) -> tuple[str, bytes | None]:
    """The landing page's markdown and its key figure (the one the README calls so, drawn in the executed
    lecturer notebook it names; None where it cannot be found, which the command says)."""
    text = readme.read_text(encoding="utf-8") if readme is not None else ""
    lessons, by_name = [], {}
    for nb in notebooks:
        data = json.loads(nb.read_text(encoding="utf-8"))
        by_name[nb.name] = data
        lessons.append((nb.name, book_reader.first_heading(data)))
    ref = book_reader.key_figure_ref(text) if text else None
    figure = book_reader.section_figure(by_name[ref[0]], ref[1]) if ref and ref[0] in by_name else None
    if text and figure is None:
        log("book: the key figure the README names was not found in the lessons; the landing page shows none")
    md = book_reader.landing_markdown(book_reader.readme_purpose(text), lessons,
                                      (KEY_FIGURE_FILE, ref[2]) if figure is not None else None,
                                      edition == "student")
    return md, figure


# --------------------------------------------------------------------------- the student edition


def _cell_source(cell: dict) -> str:
    src = cell.get("source", "")
    return "".join(src) if isinstance(src, list) else str(src)


def student_view(lecturer: dict, released: dict, name: str = "the notebook") -> dict:
    """The lesson as the student book shows it: the cells of the student release (nbgrader's: each
    solution a stub, the hidden tests gone), each with the executed lecturer notebook's outputs only
    where the release left its source as it was and it is no exercise cell (an exercise's answer and
    check cells print the solution's results). A :class:`BookError` where the cells do not match."""
    lcells, rcells = lecturer.get("cells", []), released.get("cells", [])
    if len(lcells) != len(rcells) or any(a.get("id") != b.get("id") or a.get("cell_type") != b.get("cell_type")
                                         for a, b in zip(lcells, rcells)):
        raise BookError(f"cannot build the student book: the student release of {name} does not have the "
                        "lecturer notebook's cells")
    view = json.loads(json.dumps(released))
    for shown, lect in zip(view["cells"], lcells):
        if shown.get("cell_type") != "code":
            continue
        same = _cell_source(shown) == _cell_source(lect)
        exercise_cell = bool(lect.get("metadata", {}).get("nbgrader"))
        shown["outputs"] = lect.get("outputs", []) if same and not exercise_cell else []
        shown["execution_count"] = lect.get("execution_count") if shown["outputs"] else None
    return view


def student_notebooks(notebooks: list[Path], folder: Path) -> tuple[list[Path], dict[str, Path]]:
    """(the notebooks the student book renders, the notebook each lesson links for download), written in
    ``folder``: a lesson with a solution region (``course.holds_solutions``) is released with
    ``exercises.write_release`` (nbgrader, checked for leaks) and shown by :func:`student_view`; a
    lesson without one is shown and linked as it is, as the student edition hands it out."""
    with_solutions = [nb for nb in notebooks if course.holds_solutions(nb)]
    released = {p.name: p for p in exercises.write_release(folder / "release", with_solutions)} \
        if with_solutions else {}
    utils.make_dir(folder / "shown")
    shown, downloads = [], {}
    for nb in notebooks:
        if nb.name not in released:
            shown.append(nb)
            downloads[nb.name] = nb
            continue
        lecturer = exercises.read_notebook(nb)
        view = student_view(lecturer, exercises.read_notebook(released[nb.name], solutions=False), nb.name)
        problems = exercises.leaks(lecturer, view)
        if problems:
            raise BookError(f"cannot build the student book: {nb.name} still holds solution text: {problems[0]}")
        write_file(folder / "shown" / nb.name, json.dumps(view, indent=1, ensure_ascii=False))
        shown.append(folder / "shown" / nb.name)
        downloads[nb.name] = released[nb.name]
    return shown, downloads


def run_myst(project: Path, timeout: float = BUILD_TIMEOUT_S) -> Path:
    """``jupyter-book build --site`` in ``project``; returns the folder with config.json, content/ and
    public/. A failure is a :class:`BookError` naming the last line jupyter-book printed."""
    cmd = [sys.executable, "-m", "jupyter_book", "build", "--site", "--ci"]
    env = {**os.environ, "CI": "true"}
    try:
        done = subprocess.run(cmd, cwd=project, capture_output=True, text=True, timeout=timeout, env=env,
                              stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        raise BookError(f"cannot build the book: jupyter-book build took more than {timeout:.0f} s") from None
    site = project / "_build" / "site"
    if done.returncode != 0 or not (site / "config.json").is_file():
        lines = [ln.strip() for ln in (done.stdout + "\n" + done.stderr).splitlines() if ln.strip()]
        last = next((ln for ln in reversed(lines) if "error" in ln.lower() or "failed" in ln.lower()),
                    lines[-1] if lines else "no output")
        raise BookError(f"cannot build the book: jupyter-book build failed (exit status {done.returncode}): "
                        f"{last}")
    return site


# --------------------------------------------------------------------------- package source index


@dataclass
class Module:
    """One module of the package: its dotted name (``losses``, ``datasets.c3vd``), file and symbols."""
    name: str
    path: Path
    symbols: dict[str, int] = field(default_factory=dict)  # "sdf_loss" / "Class.method" -> line

    @property
    def page(self) -> str:
        return f"{SOURCE}/{self.name}.html"


@functools.lru_cache(maxsize=4)
def index_package(package_dir: Path = PACKAGE_DIR) -> dict[str, Module]:
    """Every module of the package with the line of each top-level function, class, class method and
    assigned name (read once per process: the package's files do not change while it runs)."""
    modules: dict[str, Module] = {}
    for path in sorted(Path(package_dir).rglob("*.py")):
        rel = path.relative_to(package_dir).with_suffix("")
        if rel.name == "__main__":
            continue
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        name = ".".join(parts) or "__init__"
        mod = Module(name, path)
        try:
            tree = ast.parse(path.read_text(encoding="utf-8"))
        except (SyntaxError, OSError, UnicodeDecodeError):
            modules[name] = mod
            continue
        for node in tree.body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                mod.symbols[node.name] = node.lineno
                if isinstance(node, ast.ClassDef):
                    for sub in node.body:
                        if isinstance(sub, (ast.FunctionDef, ast.AsyncFunctionDef)):
                            mod.symbols[f"{node.name}.{sub.name}"] = sub.lineno
            elif isinstance(node, (ast.Assign, ast.AnnAssign)):
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                for t in targets:
                    if isinstance(t, ast.Name):
                        mod.symbols.setdefault(t.id, node.lineno)
        modules[name] = mod
    return modules


@dataclass
class Names:
    """What the package's names mean in one notebook: module aliases and names imported from modules."""
    modules: dict[str, str] = field(default_factory=dict)  # "losses" -> "losses"; "L" -> "losses"
    symbols: dict[str, tuple[str, str]] = field(default_factory=dict)  # "sdf_loss" -> ("losses", "sdf_loss")


def notebook_names(sources: list[str], modules: dict[str, Module]) -> Names:
    """The package names imported by a notebook's code cells (IPython magics and shell lines skipped)."""
    names = Names()
    for src in sources:
        text = "\n".join("" if ln.lstrip().startswith(("%", "!")) else ln for ln in src.splitlines())
        try:
            tree = ast.parse(text)
        except SyntaxError:
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                base = node.module
                if base == "geodepth_lite":
                    for a in node.names:
                        if a.name in modules:
                            names.modules[a.asname or a.name] = a.name
                elif base.startswith("geodepth_lite."):
                    mod = base[len("geodepth_lite."):]
                    for a in node.names:
                        if mod in modules and a.name in modules[mod].symbols:
                            names.symbols[a.asname or a.name] = (mod, a.name)
                        elif f"{mod}.{a.name}" in modules:
                            names.modules[a.asname or a.name] = f"{mod}.{a.name}"
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.startswith("geodepth_lite.") and a.asname and a.name[14:] in modules:
                        names.modules[a.asname] = a.name[14:]
    return names


def resolve(chain: list[str], names: Names, modules: dict[str, Module]) -> tuple[int, str, str] | None:
    """A dotted name (``["losses", "sdf_loss"]``) as (parts used, module, symbol or ""), or None where it
    names nothing of the package. The longest known prefix wins."""
    if not chain:
        return None
    first, used, mod = chain[0], 1, None
    if first == "geodepth_lite":
        for k in range(len(chain), 1, -1):
            if ".".join(chain[1:k]) in modules:
                mod, used = ".".join(chain[1:k]), k
                break
        if mod is None:
            return None
    elif first in names.modules:
        mod = names.modules[first]
    elif first in names.symbols:
        mod, sym = names.symbols[first]
        if len(chain) > 1 and f"{sym}.{chain[1]}" in modules[mod].symbols:
            return 2, mod, f"{sym}.{chain[1]}"
        return 1, mod, sym
    else:
        return None
    rest = chain[used:]
    for k in (2, 1):
        if len(rest) >= k and ".".join(rest[:k]) in modules[mod].symbols:
            return used + k, mod, ".".join(rest[:k])
    return used, mod, ""


# --------------------------------------------------------------------------- code highlighting with links


def _token_class(ttype) -> str:
    while ttype not in STANDARD_TYPES:
        ttype = ttype.parent
    return STANDARD_TYPES[ttype]


def _link_tokens(tokens: list, link) -> list[tuple[str, str, str | None]]:
    """Pygments tokens as (css class, text, None), with ("", "", href) opening a link around a dotted name
    of the package that ``link`` resolves and ("", "", "/") closing it."""
    pieces: list[tuple[str, str, str | None]] = []
    i = 0
    while i < len(tokens):
        ttype, value = tokens[i]
        if link is not None and ttype in Name and ttype not in Name.Namespace and value.isidentifier():
            chain, j = [value], i + 1
            while (j + 1 < len(tokens) and tokens[j] == (Operator, ".") and tokens[j + 1][0] in Name
                   and tokens[j + 1][1].isidentifier()):
                chain.append(tokens[j + 1][1])
                j += 2
            prev = next((t for t in reversed(tokens[:i]) if t[0] not in Text), None)
            found = None if prev == (Operator, ".") else link(chain)  # an attribute of something else
            if found:
                used, href = found
                pieces.append(("", "", href))
                pieces += [(_token_class(t), v, None) for t, v in tokens[i:i + 2 * used - 1]]
                pieces.append(("", "", "/"))
                i += 2 * used - 1
                continue
        if link is not None and ttype in Name.Namespace and value.startswith("geodepth_lite."):
            found = link(value.split("."))
            if found:
                pieces += [("", "", found[1]), (_token_class(ttype), value, None), ("", "", "/")]
                i += 1
                continue
        pieces.append((_token_class(ttype), value, None))
        i += 1
    return pieces


def highlight_lines(code: str, lang: str = "python", link=None) -> list[str]:
    """``code`` as highlighted HTML, one string per line. ``link(chain) -> (parts used, href) | None``
    turns a dotted name of the code into a link to its source."""
    try:
        lexer = get_lexer_by_name(lang or "text", stripnl=False, ensurenl=False)
    except ClassNotFound:
        lexer = get_lexer_by_name("text", stripnl=False, ensurenl=False)
    lines, cur, open_href = [], [], None
    for cls, text, href in _link_tokens(list(lexer.get_tokens(code)), link):
        if href == "/":
            cur.append("</a>")
            open_href = None
            continue
        if href:
            cur.append(f'<a class="src" href="{html.escape(href)}">')
            open_href = href
            continue
        for k, part in enumerate(text.split("\n")):
            if k:  # a new line: close the open link and reopen it there, so that each line is whole HTML
                if open_href:
                    cur.append("</a>")
                lines.append("".join(cur))
                cur = [f'<a class="src" href="{html.escape(open_href)}">'] if open_href else []
            if part:
                esc = html.escape(part, quote=False)
                cur.append(f'<span class="{cls}">{esc}</span>' if cls else esc)
    lines.append("".join(cur))
    if code.endswith("\n") and lines and lines[-1] == "":
        lines.pop()
    return lines


def split_folds(code: str) -> list[tuple[str, int, int]]:
    """The line ranges of a cell's code: ``("code", a, b)`` shown, ``("solution", a, b)`` and
    ``("hidden", a, b)`` folded (the marker lines themselves are left out)."""
    lines = code.split("\n")
    out, start, kind = [], 0, "code"
    begins = {SOLUTION_MARKERS[0]: "solution", HIDDEN_MARKERS[0]: "hidden"}
    ends = {SOLUTION_MARKERS[1]: "solution", HIDDEN_MARKERS[1]: "hidden"}
    for i, line in enumerate(lines):
        s = line.strip()
        if kind == "code" and s in begins:
            out.append(("code", start, i))
            kind, start = begins[s], i + 1
        elif kind != "code" and ends.get(s) == kind:
            out.append((kind, start, i))
            kind, start = "code", i + 1
    out.append((kind, start, len(lines)))
    return [(k, a, b) for k, a, b in out if b > a or k != "code"]


# --------------------------------------------------------------------------- HTML the book did not write

SAFE_TAGS = frozenset("a abbr b blockquote br caption code col colgroup dd del details div dl dt em figcaption figure "
                      "h1 h2 h3 h4 h5 h6 hr i img ins kbd li mark ol p pre q s samp small span strong sub summary sup "
                      "table tbody td tfoot th thead tr tt u ul var".split())
VOID_TAGS = frozenset({"br", "col", "hr", "img"})
# elements whose content is dropped with them: scripts, styles, embedded documents, SVG and MathML (their
# own attributes and elements run script), and those a browser reads as raw text (noscript, textarea, ...)
DROPPED_TAGS = frozenset("script style template iframe frameset object applet svg math noscript noembed noframes "
                         "textarea title xmp plaintext select head audio video canvas".split())
SAFE_ATTRS = {"class": r"[\w -]{0,200}", "title": r"[^\x00]{0,500}", "alt": r"[^\x00]{0,500}",
              "align": r"left|right|center|justify", "valign": r"top|middle|bottom|baseline",
              "colspan": r"\d{1,4}", "rowspan": r"\d{1,4}", "span": r"\d{1,4}", "start": r"-?\d{1,9}",
              "width": r"\d{1,5}%?", "height": r"\d{1,5}%?", "border": r"\d{1,3}",
              "scope": r"row|col|rowgroup|colgroup"}
URL_ATTRS = {"a": "href", "img": "src"}
LINK_SCHEMES = ("http", "https", "mailto")
IMAGE_DATA = re.compile(r"^data:image/(?:png|jpeg|gif|webp);base64,[a-z0-9+/=]+$")


def safe_url(url: str, image: bool = False) -> str | None:
    """``url`` where following it runs no script: a relative URL, http(s) or mailto (an image: http(s) or a
    base64 PNG/JPEG/GIF/WebP data URL); None for javascript:, vbscript:, other data: URLs and the like.
    The scheme is read as a browser reads it: control characters and white space anywhere are ignored."""
    squeezed = re.sub(r"[\x00-\x20\x7f]+", "", url).lower()
    m = re.match(r"^([a-z][a-z0-9+.\-]*):", squeezed)
    if m is None:
        return None if squeezed.startswith(("\\", "/\\")) else url.strip()
    if image:
        return url.strip() if m.group(1) in ("http", "https") or IMAGE_DATA.match(squeezed) else None
    return url.strip() if m.group(1) in LINK_SCHEMES else None


class _Sanitiser(html.parser.HTMLParser):
    """Re-writes HTML keeping only :data:`SAFE_TAGS` with :data:`SAFE_ATTRS` (values matched whole) and safe
    URLs; every text is escaped again, so the output holds no markup but what this class writes."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.out: list[str] = []
        self.open: list[str] = []
        self.dropping = 0  # depth inside DROPPED_TAGS

    def handle_starttag(self, tag, attrs):
        if tag in DROPPED_TAGS:
            self.dropping += tag not in VOID_TAGS
            return
        if self.dropping or tag not in SAFE_TAGS:
            return
        kept = []
        for name, value in attrs:
            value = "" if value is None else value
            if URL_ATTRS.get(tag) == name:
                value = safe_url(value, image=tag == "img")
            elif name not in SAFE_ATTRS or not re.fullmatch(SAFE_ATTRS[name], value):
                value = None
            if value is not None:
                kept.append(f' {name}="{html.escape(value)}"')
        if tag == "a":
            kept.append(' rel="noopener noreferrer nofollow"')
        self.out.append(f"<{tag}{''.join(kept)}>")
        if tag not in VOID_TAGS:
            self.open.append(tag)

    def handle_startendtag(self, tag, attrs):
        self.handle_starttag(tag, attrs)
        if tag not in VOID_TAGS and tag not in DROPPED_TAGS:
            self.handle_endtag(tag)
        elif tag in DROPPED_TAGS and tag not in VOID_TAGS:
            self.dropping -= 1

    def handle_endtag(self, tag):
        if tag in DROPPED_TAGS:
            self.dropping = max(self.dropping - 1, 0)
        elif not self.dropping and tag in self.open:
            while self.open:
                last = self.open.pop()
                self.out.append(f"</{last}>")
                if last == tag:
                    break

    def handle_data(self, data):
        if not self.dropping:
            self.out.append(html.escape(data, quote=False))

    def result(self) -> str:
        self.close()
        return "".join(self.out) + "".join(f"</{t}>" for t in reversed(self.open))


def sanitise_html(doc: str) -> str:
    """HTML a notebook output (or a page's raw HTML) holds, with everything that can run script taken out:
    see :class:`_Sanitiser`. Tables, text formatting, links and data-URL images stay."""
    parser = _Sanitiser()
    parser.feed(doc)
    return parser.result()


def framed_html(doc: str) -> str:
    """An HTML output that is a whole document or carries script, shown in an iframe that the browser
    sandboxes fully (``sandbox=""``: no script, no same origin, no forms, no pop-ups, no top navigation)."""
    return (f'<iframe class="output-html" sandbox="" srcdoc="{html.escape(doc)}" style="width:100%;height:520px;'
            f'border:1px solid #d9dee7" loading="eager"></iframe>')


# --------------------------------------------------------------------------- rendering MyST content

ANSI = re.compile(r"\x1b\[[0-9;?]*[ -/]*[@-~]")
FOLD_LABEL = {"solution": "Show solution", "hidden": "Show the hidden tests"}
INLINE_CODE = re.compile(r"^(?:geodepth_lite[./])?([A-Za-z_][\w]*(?:\.[A-Za-z_]\w*)*)(?:\(.*\))?$")


class PageRenderer:
    """Renders one page's MyST content (mdast) to HTML, collecting the package names it links."""

    def __init__(self, site: "Site", slug: str, names: Names):
        self.site, self.slug, self.names = site, slug, names
        self.used: dict[tuple[str, str], None] = {}  # (module, symbol) in order of first use
        self.headings: list[tuple[int, str, str]] = []  # (depth, id, text), for "on this page"

    # links into the source pages
    def source_href(self, mod: str, sym: str) -> str:
        self.used.setdefault((mod, sym), None)
        module = self.site.modules[mod]
        anchor = f"#L{module.symbols[sym]}" if sym else ""
        return f"{module.page}{anchor}"

    def link_chain(self, chain: list[str]):
        found = resolve(chain, self.names, self.site.modules)
        if found is None:
            return None
        used, mod, sym = found
        return used, self.source_href(mod, sym)

    def bare_modules(self) -> dict[str, str]:
        """A module's short name in prose (``losses``, ``predict``) -> its name in the wings (``core.losses``,
        ``apps.predict``); the package's top-level modules (``utils``, ``cli``) by their own names."""
        bare = {k.rpartition(".")[2]: k for k in self.site.modules if k.count(".") == 1}
        bare.update({k: k for k in self.site.modules if "." not in k})
        return bare

    def inline_code_link(self, value: str) -> str | None:
        text = value.strip()
        bare = self.bare_modules()
        m = re.match(r"^(?:geodepth_lite/)?([\w/]+)\.py$", text)
        if m and bare.get(m.group(1).replace("/", "."), m.group(1).replace("/", ".")) in self.site.modules:
            return self.source_href(bare.get(m.group(1).replace("/", "."), m.group(1).replace("/", ".")), "")
        m = INLINE_CODE.match(text)
        if not m:
            return None
        chain = m.group(1).split(".")
        if text.startswith(("geodepth_lite.", "geodepth_lite/")):
            chain = ["geodepth_lite", *chain]
        names = Names({**bare, **self.names.modules}, self.names.symbols)
        found = resolve(chain, names, self.site.modules)
        if found is None:
            return None
        used, mod, sym = found
        if used != len(chain) or (not sym and chain[0] != "geodepth_lite"):
            return None  # "losses" alone or "config.unknown": not clearly the package's name
        return self.source_href(mod, sym)

    # the tree
    def children(self, node: dict) -> str:
        return "".join(self.node(c) for c in node.get("children", []) or [])

    def node(self, n: dict) -> str:
        t = n.get("type", "")
        if t in INLINE_TAGS:  # phrasing nodes that map to one HTML element around their children
            return f"<{INLINE_TAGS[t]}>{self.children(n)}</{INLINE_TAGS[t]}>"
        fn = getattr(self, "n_" + t, None)
        if fn is not None:
            return fn(n)
        if "children" in n:
            return self.children(n)
        return html.escape(str(n.get("value", "")), quote=False)

    def n_root(self, n):
        return self.children(n)

    def n_block(self, n):
        if n.get("visibility") == "remove":
            return ""
        tags = ((n.get("data") or {}).get("tags")) or []
        hid = html.escape(n.get("html_id") or n.get("identifier") or "")
        if n.get("kind") == "notebook-code":
            return self.code_cell(n, SOLUTION_TAG in tags, hid)
        body = self.children(n)
        if SOLUTION_TAG in tags:  # a markdown answer (open-ended exercise): the whole cell folds away
            body = f'<details class="solution"><summary>{FOLD_LABEL["solution"]}</summary>{body}</details>'
        return f'<div class="block" id="{hid}">{body}</div>' if hid else body

    def code_cell(self, n, solution: bool, hid: str) -> str:
        code_node = next((c for c in n.get("children", []) if c.get("type") == "code"), None)
        outputs = [c for c in n.get("children", []) if c.get("type") == "outputs"]
        parts = []
        if code_node is not None:
            code = code_node.get("value", "")
            lines = highlight_lines(code, code_node.get("lang") or "python", self.link_chain)
            for kind, a, b in split_folds(code):
                pre = "<pre><code>" + "\n".join(lines[a:b]) + "</code></pre>"
                if kind == "code":
                    parts.append(pre)
                else:
                    parts.append(f'<details class="{"solution" if kind == "solution" else "hidden-tests"}">'
                                 f'<summary>{FOLD_LABEL[kind]}</summary>{pre}</details>')
        out_html = "".join(self.n_outputs(o) for o in outputs)
        body = f'<div class="cell-input">{"".join(parts)}</div>'
        if out_html:
            out_div = f'<div class="cell-outputs">{out_html}</div>'
            if solution:  # the outputs of a solution's cell give the answer away too
                out_div = (f'<details class="solution"><summary>Show the output of the solution</summary>'
                           f'{out_div}</details>')
            body += out_div
        return f'<div class="cell" id="{hid}">{body}</div>'

    def n_outputs(self, n):
        return "".join(self.output(c.get("jupyter_data") or {}) for c in n.get("children", []))

    def output_text(self, value: dict) -> str:
        if "content" in value:
            return str(value["content"])
        return self.site.public_text(value.get("path", ""))

    def plotly_figure(self, value) -> dict | None:
        """A plotly figure as the notebook stored it, or as jupyter-book wrote it (inline or a file)."""
        if isinstance(value, dict) and "data" in value:
            return value
        text = self.output_text(value) if isinstance(value, dict) else str(value)
        try:
            figure = json.loads(text)
        except ValueError:
            return None
        return figure if isinstance(figure, dict) and "data" in figure else None

    def output(self, jd: dict) -> str:
        kind = jd.get("output_type")
        if kind == "stream":
            text = ANSI.sub("", "".join(jd.get("text", "")) if isinstance(jd.get("text"), list)
                            else str(jd.get("text", "")))
            if jd.get("name") == "stderr":
                return f'<pre class="stderr">{html.escape(text, quote=False)}</pre>'
            return book_reader.printed_html(text, "stdout")  # a printed pipe table as a table
        if kind == "error":
            tb = "\n".join(jd.get("traceback") or [f"{jd.get('ename')}: {jd.get('evalue')}"])
            return f'<pre class="stderr">{html.escape(ANSI.sub("", tb), quote=False)}</pre>'
        data = jd.get("data") or {}
        if recon.PLOTLY_MIME in data:  # an interactive 3D view: plotly.js, served from _static, draws it
            figure = self.plotly_figure(data[recon.PLOTLY_MIME])
            if figure is not None:
                return recon.plotly_html(figure)
        for mime in ("image/png", "image/jpeg", "image/gif", "image/svg+xml"):
            if mime in data:
                src = self.site.image(data[mime], mime)
                if src:
                    return f'<img src="{html.escape(src)}" alt="a figure the cell drew">'
        if "text/html" in data:
            doc = self.output_text(data["text/html"])
            if "<script" in doc.lower() or "<html" in doc.lower():
                return framed_html(doc)
            return f'<div class="output-html">{sanitise_html(doc)}</div>'
        if "application/vnd.jupyter.widget-view+json" in data:
            return ('<p class="widget-note"><em>An interactive widget: run the notebook in JupyterLab to use '
                    'it.</em></p>')
        if "text/plain" in data:
            return book_reader.printed_html(ANSI.sub("", self.output_text(data["text/plain"])))
        return ""

    def n_heading(self, n):
        d = min(max(int(n.get("depth", 2)), 1), 6)
        ident = n.get("html_id") or n.get("identifier") or ""
        inner = self.children(n)
        self.headings.append((d, ident, " ".join(book_reader.strip_tags(inner).split())))
        return f'<h{d} id="{html.escape(ident)}">{inner}</h{d}>'

    def n_paragraph(self, n):
        return f"<p>{self.children(n)}</p>"

    def n_text(self, n):
        return html.escape(n.get("value", ""), quote=False)

    def n_break(self, n):
        return "<br>"

    def n_thematicBreak(self, n):
        return "<hr>"

    def n_blockquote(self, n):
        return f"<blockquote>{self.children(n)}</blockquote>"

    def n_inlineCode(self, n):
        value = n.get("value", "")
        code = f"<code>{html.escape(value, quote=False)}</code>"
        href = self.inline_code_link(value)
        return f'<a class="src" href="{html.escape(href)}">{code}</a>' if href else code

    def n_code(self, n):
        lines = highlight_lines(n.get("value", ""), n.get("lang") or "text", None)
        return "<pre><code>" + "\n".join(lines) + "</code></pre>"

    def n_list(self, n):
        if n.get("ordered"):
            start = n.get("start")
            attr = f' start="{int(start)}"' if isinstance(start, int) and start != 1 else ""
            return f"<ol{attr}>{self.children(n)}</ol>"
        return f"<ul>{self.children(n)}</ul>"

    def n_listItem(self, n):
        return f"<li>{self.children(n)}</li>"

    def n_table(self, n):
        return f"<table>{self.children(n)}</table>"

    def n_tableRow(self, n):
        return f"<tr>{self.children(n)}</tr>"

    def n_tableCell(self, n):
        tag = "th" if n.get("header") else "td"
        align = n.get("align")
        style = f' style="text-align:{align}"' if align in ("left", "right", "center") else ""
        return f"<{tag}{style}>{self.children(n)}</{tag}>"

    def n_inlineMath(self, n):
        if n.get("html"):
            return f'<span class="math-inline">{n["html"]}</span>'
        return f'<code class="math-error">{html.escape(n.get("value", ""), quote=False)}</code>'

    def n_math(self, n):
        number = f'<span class="eq-number">({html.escape(str(n["enumerator"]))})</span>' if n.get(
            "enumerator") else ""
        hid = html.escape(n.get("html_id") or n.get("identifier") or "")
        ident = f' id="{hid}"' if hid else ""
        if n.get("html"):
            return f'<div class="math-display"{ident}>{number}{n["html"]}</div>'
        return f'<pre class="math-error"{ident}>{html.escape(n.get("value", ""), quote=False)}</pre>'

    def href(self, url: str) -> str | None:
        """A page's link as a link of the site, or None where it points at a file the site does not hold."""
        if re.match(r"^[a-z][a-z0-9+.-]*:", re.sub(r"[\x00-\x20\x7f]+", "", url).lower()):
            return safe_url(url)  # http(s), mailto; None (named, not linked) for javascript: and the like
        if url.startswith("#"):
            return url
        if url.startswith("/"):
            slug, _, anchor = url[1:].partition("#")
            if slug in self.site.slugs:
                return f"{slug or 'index'}.html" + (f"#{anchor}" if anchor else "")
        m = re.match(r"^(?:\.\./|\./)*(?:geodepth_lite/)([\w/]+)\.py(?:#L?(\d+))?$", url)
        if m and m.group(1).replace("/", ".") in self.site.modules:
            mod = m.group(1).replace("/", ".")
            self.used.setdefault((mod, ""), None)
            return self.site.modules[mod].page + (f"#L{m.group(2)}" if m.group(2) else "")
        return None

    def n_link(self, n):
        url = n.get("url", "")
        href = self.href(url)
        body = self.children(n) or html.escape(url, quote=False)
        if href is None:  # a file of the checkout that the book does not hold: named, not linked
            return f'<span class="repo-file" title="in the repository: {html.escape(url)}">{body}</span>'
        return f'<a href="{html.escape(href)}">{body}</a>'

    def n_crossReference(self, n):
        href = self.href(n.get("url", "")) if n.get("url") else None
        hid = n.get("html_id") or n.get("identifier")
        if href is None:
            href = f"#{hid}" if hid else None
        elif hid and "#" not in href:
            href += f"#{hid}"
        body = self.children(n) or html.escape(str(n.get("label") or hid or ""), quote=False)
        return f'<a href="{html.escape(href)}">{body}</a>' if href else body

    def n_image(self, n):
        src = self.site.image({"path": n.get("url", "")}, "")
        alt = html.escape(n.get("alt") or "figure")
        return f'<img src="{html.escape(src)}" alt="{alt}">' if src else f"<em>[figure: {alt}]</em>"

    def n_admonition(self, n):
        kids = n.get("children", [])
        title = next((c for c in kids if c.get("type") == "admonitionTitle"), None)
        rest = [c for c in kids if c is not title]
        head = (f'<p class="admonition-title">{self.children(title)}</p>' if title else
                f'<p class="admonition-title">{html.escape(str(n.get("kind", "note")).title())}</p>')
        return f'<div class="admonition {html.escape(str(n.get("kind", "")))}">{head}' \
               f'{"".join(self.node(c) for c in rest)}</div>'

    def n_html(self, n):
        return sanitise_html(str(n.get("value", "")))  # raw HTML in markdown: kept only where it runs no script

    def n_footnoteReference(self, n):
        ident = html.escape(str(n.get("identifier", "")))
        return f'<sup><a href="#fn-{ident}">{html.escape(str(n.get("enumerator", ident)))}</a></sup>'

    def n_footnoteDefinition(self, n):
        ident = html.escape(str(n.get("identifier", "")))
        return f'<div class="footnote" id="fn-{ident}">{self.children(n)}</div>'

    def n_comment(self, n):
        return ""


# --------------------------------------------------------------------------- the site


class Site:
    """The rendered site: reads MyST's output in ``build`` and writes the HTML into ``dest``."""

    def __init__(self, build: Path, dest: Path, modules: dict[str, Module], lesson_names: dict[str, Names],
                 katex: bool, downloads: dict[str, str] | None = None, edition: str = "lecturer",
                 released: frozenset[str] = frozenset()):
        self.build, self.dest, self.modules = Path(build), Path(dest), modules
        self.lesson_names, self.katex = lesson_names, katex
        self.downloads = downloads or {}  # page slug -> the notebook's file name under notebooks/
        self.edition, self.released = edition, released  # released: the notebooks linked as the student release
        self.search: list[dict] = []  # the search index's pages, as they are written
        config = json.loads((self.build / "config.json").read_text(encoding="utf-8"))
        project = (config.get("projects") or [{}])[0]
        self.index_slug = project.get("index", "index")
        self.nav: list[dict] = [{"slug": self.index_slug, "title": "Home", "level": 1}] + [
            p for p in project.get("pages", []) if p.get("slug") != self.index_slug]
        self.slugs = {p["slug"] for p in self.nav if p.get("slug")} | {""}
        self.images: set[str] = set()
        self.usage: dict[tuple[str, str], list[tuple[str, str]]] = {}  # (module, symbol) -> [(page, title)]

    def public_text(self, path: str) -> str:
        src = bounds.inside_folder(self.build / "public", path.lstrip("/"))
        if src is None or not src.is_file() or src.stat().st_size > MAX_PAGE_JSON_BYTES:
            return ""
        return src.read_text(encoding="utf-8", errors="replace")

    def image(self, value: dict, mime: str) -> str | None:
        """Copy a figure MyST wrote out into _static/img; its URL from a top-level page."""
        path = str(value.get("path", "")).lstrip("/")
        if not path and value.get("content") and mime in ("image/png", "image/jpeg", "image/gif"):
            try:
                raw = base64.b64decode(value["content"])
            except ValueError:
                return None
            path = hashlib.sha256(raw).hexdigest()[:32] + "." + mime.split("/")[1]
            target = self.dest / STATIC / "img" / path
            if not target.exists():
                utils.make_dir(target.parent)
                write_file(target, raw)
            return f"{STATIC}/img/{path}"
        src = bounds.inside_folder(self.build / "public", path) if path else None
        if src is None or not src.is_file():
            return None
        target = self.dest / STATIC / "img" / src.name
        if src.name not in self.images:
            utils.make_dir(target.parent)
            copy_file(src, target)
            self.images.add(src.name)
        return f"{STATIC}/img/{src.name}"

    def page_json(self, slug: str) -> dict:
        path = self.build / "content" / f"{slug}.json"
        if not path.is_file() or path.stat().st_size > MAX_PAGE_JSON_BYTES:
            raise BookError(f"cannot render the book: jupyter-book wrote no page content {path.name}")
        return json.loads(path.read_text(encoding="utf-8"))

    def head(self, title: str, prefix: str) -> str:
        css = [f"{prefix}{STATIC}/book.css", f"{prefix}{STATIC}/pygments.css"]
        if self.katex:
            css.insert(0, f"{prefix}{STATIC}/katex/katex.min.css")
        links = "".join(f'<link rel="stylesheet" href="{h}">' for h in css)
        return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
                f'<meta name="viewport" content="width=device-width, initial-scale=1"><link rel="icon" href="data:,">'
                f'<title>{html.escape(title)} · geodepth-lite</title>{links}</head>')

    def sidebar(self, current: str, prefix: str) -> str:
        items = []
        for p in self.nav:
            title = html.escape(p.get("title", ""))
            if not p.get("slug"):
                items.append(f'<li class="group">{title}</li>')
                continue
            cls = ' class="current"' if p["slug"] == current else ""
            items.append(f'<li{cls}><a href="{prefix}{p["slug"]}.html">{title}</a></li>')
        items.append('<li class="group">Source</li>')
        cls = ' class="current"' if current == "source-index" else ""
        items.append(f'<li{cls}><a href="{prefix}{SOURCE}/index.html">The package&#8217;s modules</a></li>')
        search = ('<form class="search" role="search"><input id="search-input" type="search" placeholder="Search the '
                  'book" aria-label="Search the book" autocomplete="off"></form><ul id="search-results" '
                  'class="search-results" aria-live="polite"></ul>')
        return (f'<nav class="sidebar" id="sidebar"><a class="book-title" href="{prefix}index.html">geodepth-lite'
                f'{self.edition_label()}</a>{search}<ul>{"".join(items)}</ul></nav>')

    def edition_label(self) -> str:
        return "<small>student edition</small>" if self.edition == "student" else ""

    def write_page(self, rel: str, title: str, current: str, body: str) -> None:
        prefix = "../" * rel.count("/")
        scripts = (f'<script src="{prefix}{STATIC}/{PLOTLY_JS}"></script>' if 'class="geodepth-3d"' in body
                   else "")  # plotly.js only on pages with a 3D view
        scripts += f'<script src="{prefix}{STATIC}/{BOOK_JS_FILE}"></script>'
        topbar = ('<header class="topbar"><button class="menu-toggle" type="button" aria-controls="sidebar" '
                  f'aria-expanded="false">&#9776; Contents</button><a class="topbar-title" href="{prefix}index.html">'
                  'geodepth-lite</a></header>')
        doc = (f'{self.head(title, prefix)}<body data-root="{prefix}">{topbar}<div class="layout">'
               f'{self.sidebar(current, prefix)}<main>{body}</main></div>{scripts}</body></html>\n')
        target = self.dest / rel
        utils.make_dir(target.parent)
        write_file(target, doc)
        self.search.append({"t": title, "u": rel, "s": book_reader.page_sections(body)})

    def download_link(self, slug: str) -> str:
        name = self.downloads.get(slug)
        if not name:
            return ""
        what = ("the student edition: the exercises to solve, outputs cleared" if name in self.released
                else "executed, with the outputs shown here")
        return (f'<p class="download"><a href="notebooks/{html.escape(name)}" download>Download the notebook '
                f'<code>{html.escape(name)}</code></a> ({what})</p>')

    def render_pages(self) -> list[str]:
        pages = [p for p in self.nav if p.get("slug")]
        written = []
        for k, p in enumerate(pages):
            slug = p["slug"]
            data = self.page_json(slug)
            fm = data.get("frontmatter") or {}
            title = fm.get("title") or p.get("title") or slug
            r = PageRenderer(self, slug, self.lesson_names.get(slug, Names()))
            body = r.node(data.get("mdast") or {})
            head = f"<h1>{html.escape(title)}</h1>" if not fm.get("content_includes_title", False) else ""
            extra = self.download_link(slug) + book_reader.page_toc(r.headings)
            if head:
                body = head + extra + body
            else:  # MyST kept the title as the page's first heading: the link and the list go after it
                m = re.match(r"^(?:<div[^>]*>)?<h1[^>]*>.*?</h1>", body, re.S)
                body = body[:m.end()] + extra + body[m.end():] if m else extra + body
            if r.used and data.get("kind") == "Notebook":
                body += self.used_list(r.used)
            for key in r.used:
                self.usage.setdefault(key, [])
                if (slug, title) not in self.usage[key]:
                    self.usage[key].append((slug, title))
            body += self.pager(pages, k)
            self.write_page(f"{slug}.html", title, slug, body)
            written.append(f"{slug}.html")
        return written

    @staticmethod
    def pager(pages: list[dict], k: int) -> str:
        links = []
        if k > 0:
            links.append(f'<a href="{pages[k - 1]["slug"]}.html">&larr; {html.escape(pages[k - 1]["title"])}</a>')
        if k + 1 < len(pages):
            links.append(f'<a href="{pages[k + 1]["slug"]}.html">{html.escape(pages[k + 1]["title"])} &rarr;</a>')
        return f'<div class="pager">{"".join(links)}</div>'

    def used_list(self, used: dict[tuple[str, str], None]) -> str:
        items = []
        for mod, sym in sorted(used, key=lambda ms: (ms[0], ms[1])):
            if not sym:
                continue
            module = self.modules[mod]
            items.append(f'<li><a class="src" href="{module.page}#L{module.symbols[sym]}"><code>{html.escape(mod)}.'
                         f'{html.escape(sym)}</code></a></li>')
        if not items:
            return ""
        return ('<section class="used-functions"><h2 id="package-functions-used">Package functions used in this '
                f'lesson</h2><p>Each links to its source.</p><ul>{"".join(items)}</ul></section>')

    def render_sources(self) -> list[str]:
        written = []
        rows = []
        for name, mod in sorted(self.modules.items()):
            code = mod.path.read_text(encoding="utf-8")
            lines = highlight_lines(code, "python", None)
            body_lines = []
            for i, line in enumerate(lines, start=1):
                body_lines.append(f'<span class="line" id="L{i}"><a class="ln" href="#L{i}">{i}</a>{line}</span>')
            uses = []
            for sym in sorted(mod.symbols, key=mod.symbols.get):
                pages = self.usage.get((name, sym))
                if pages:
                    links = ", ".join(f'<a href="../{s}.html">{html.escape(t)}</a>' for s, t in pages)
                    uses.append(f'<li><a href="#L{mod.symbols[sym]}"><code>{html.escape(sym)}</code></a>: '
                                f"{links}</li>")
            used_html = (f'<h2 id="used-in-lessons">Used in the lessons</h2><ul>{"".join(uses)}</ul>'
                         if uses else "")
            rel_file = mod.path.relative_to(PACKAGE_DIR.parent).as_posix()
            body = (f"<h1><code>geodepth_lite.{html.escape(name)}</code></h1>"
                    f"<p>The source of <code>{html.escape(rel_file)}</code>, as the book was built; each line has "
                    f"an anchor (<code>#L12</code>).</p>{used_html}"
                    f'<h2 id="source">Source</h2><pre class="source-code"><code>{"".join(body_lines)}</code></pre>')
            self.write_page(mod.page, f"geodepth_lite.{name}", "source-index", body)
            written.append(mod.page)
            rows.append(f'<li><a href="{html.escape(name)}.html"><code>{html.escape(name)}</code></a> '
                        f"({len(mod.symbols)} names, {len(lines)} lines; "
                        f"{sum(1 for s in mod.symbols if (name, s) in self.usage)} used in the lessons)</li>")
        self.write_page(f"{SOURCE}/index.html", "The package's modules", "source-index",
                        "<h1>The package&#8217;s modules</h1><p>The source of every module of "
                        f"<code>geodepth_lite</code>, with line anchors.</p><ul>{''.join(rows)}</ul>")
        written.append(f"{SOURCE}/index.html")
        return written

    def write_search_index(self) -> int:
        """``_static/search-index.js`` from the pages written; its size in bytes."""
        text = book_reader.search_index_js(self.search)
        write_file(self.dest / STATIC / SEARCH_INDEX, text)
        return len(text.encode("utf-8"))

    def write_static(self, katex_dir: Path | None) -> None:
        static = utils.make_dir(self.dest / STATIC)
        write_file(static / "book.css", CSS + ("" if katex_dir else MATHML_CSS))
        write_file(static / BOOK_JS_FILE, book_reader.BOOK_JS)
        write_file(static / "pygments.css", HtmlFormatter(style="default").get_style_defs("pre"))
        if katex_dir:
            for src in sorted(p for p in katex_dir.rglob("*") if p.is_file()):
                target = static / "katex" / src.relative_to(katex_dir)
                utils.make_dir(target.parent)
                copy_file(src, target)
        plotly_js = plotly_js_file()
        if plotly_js is not None:
            copy_file(plotly_js, static / PLOTLY_JS)


def plotly_js_file() -> Path | None:
    """plotly.js as the installed plotly package ships it (offline), or None without plotly."""
    spec = importlib.util.find_spec("plotly")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(list(spec.submodule_search_locations)[0]) / "package_data" / PLOTLY_JS
    return path if path.is_file() else None


# --------------------------------------------------------------------------- KaTeX's style sheet and fonts


def katex_cache() -> Path:
    return utils.data_dir() / "book" / f"katex-{KATEX_VERSION}.tgz"


def _sri(data: bytes) -> str:
    return "sha512-" + base64.b64encode(hashlib.sha512(data).digest()).decode()


def fetch_katex(cache: Path, npm: str | None = None) -> tuple[Path | None, str]:
    """The KaTeX npm package's tarball (from ``cache``, or fetched there by ``npm pack``), checked
    against :data:`KATEX_INTEGRITY`; (None, why) where it cannot be had."""
    if cache.is_file() and cache.stat().st_size <= KATEX_MAX_BYTES and _sri(cache.read_bytes()) == KATEX_INTEGRITY:
        return cache, ""
    npm = npm or shutil.which("npm")
    if npm is None:
        return None, "npm is not on PATH"
    with tempfile.TemporaryDirectory(prefix=f"geodepth-katex-{os.getpid()}-") as tmp:
        try:
            done = subprocess.run([npm, "pack", f"katex@{KATEX_VERSION}", "--pack-destination", tmp, "--silent"],
                                  capture_output=True, text=True, timeout=300, cwd=tmp, stdin=subprocess.DEVNULL)
        except (OSError, subprocess.SubprocessError) as exc:
            return None, f"npm pack failed: {exc}"
        found = sorted(Path(tmp).glob("katex-*.tgz"))
        if done.returncode != 0 or not found:
            lines = [ln for ln in (done.stderr + done.stdout).splitlines() if ln.strip()]
            return None, f"npm pack katex@{KATEX_VERSION} failed: {lines[-1] if lines else done.returncode}"
        if found[0].stat().st_size > KATEX_MAX_BYTES:
            return None, f"npm pack katex@{KATEX_VERSION} gave a file over {KATEX_MAX_BYTES} bytes"
        data = found[0].read_bytes()
        if _sri(data) != KATEX_INTEGRITY:
            return None, f"katex@{KATEX_VERSION} from npm does not match its pinned hash"
        utils.make_dir(cache.parent)
        utils.write_bytes_atomic(cache, data)
    return cache, ""


KATEX_MEMBER = re.compile(r"^package/dist/(katex\.min\.css|fonts/KaTeX_[A-Za-z0-9_-]+\.(?:woff2|woff|ttf))$")


def extract_katex(tgz: Path, dest: Path) -> Path:
    """katex.min.css and its fonts from the npm tarball into ``dest`` (only those regular files, each
    bounded)."""
    utils.make_dir(dest / "fonts")
    n = 0
    with tarfile.open(tgz, "r:gz") as tar:
        for member in tar:
            m = KATEX_MEMBER.match(member.name)
            if not m or not member.isfile() or member.size > 2 * 2**20:
                continue
            src = tar.extractfile(member)
            if src is None:
                continue
            write_file(dest / m.group(1), src.read(2 * 2**20))
            n += 1
    if not (dest / "katex.min.css").is_file() or n < 2:
        raise BookError(f"cannot read {tgz}: it holds no katex.min.css with fonts")
    return dest


# --------------------------------------------------------------------------- the command


def build(out: Path, *, notebooks: list[Path] | None = None, docs: list[Path] | None = None,
          readme: Path | None = README, katex: bool = True, edition: str = "lecturer", log=print) -> dict:
    """Build the book into ``out``; returns the summary the marker holds (pages, figures, math).

    ``edition``: "lecturer" (the executed notebooks, solutions folded) or "student" (the same outputs, but
    no solution, no solution output and no hidden test: :func:`student_notebooks`).

    ``out`` is checked (:func:`check_out`), locked (``utils.FolderLock``) and filled only when the
    whole site is rendered: the site is made in a hidden folder inside ``out`` and moved in at the end.
    """
    check_node()
    check_jupyter_book()
    notebooks = lesson_notebooks() if notebooks is None else [Path(p) for p in notebooks]
    docs = sorted(DOCS_DIR.glob("*.md")) if docs is None else [Path(p) for p in docs]
    readme = Path(readme) if readme is not None and Path(readme).is_file() else None
    if not notebooks:
        raise BookError(f"cannot build the book: no notebook NN_name.ipynb under {NOTEBOOK_DIR}")
    if edition not in EDITIONS:
        raise BookError(f"cannot build the book: --edition {edition!r} is not one of {', '.join(EDITIONS)}")
    out = Path(out)
    check_out(out)
    created = utils.missing_dirs(out)
    utils.check_output_dir(out)
    lock = utils.FolderLock(out, "book folder", remove_file=True)
    new = out / f"{NEW_DIR}-{os.getpid()}"
    publishing = False
    try:
        lock.acquire()
        check_out(out)  # again, under the lock
        remove_stale_staging(out, STAGING)  # what a killed build left, here and in the temporary folder
        remove_stale_staging(Path(tempfile.gettempdir()))
        if new.exists():
            shutil.rmtree(new)
        summary = _make_site(new, notebooks, docs, readme, katex, log, edition)
        owned, new_files = _plan(out, new)
        publishing = True
        _publish(out, new, owned, new_files, summary)
    except BaseException:
        with contextlib.suppress(OSError):
            if new.exists():
                shutil.rmtree(new)
            if publishing:
                _clear_site(out)
        lock.release()
        if not publishing and read_marker(out) is None:
            utils.remove_empty_dirs(created)
        raise
    lock.release()
    return summary


def _make_site(new: Path, notebooks: list[Path], docs: list[Path], readme: Path | None, katex: bool,
               log, edition: str = "lecturer") -> dict:
    """Stage, build with MyST and render the whole site into ``new``; returns the summary."""
    with tempfile.TemporaryDirectory(prefix=f"geodepth-book-{os.getpid()}-") as tmp:
        project = Path(tmp, "project")
        if edition == "student":
            log(f"book: the student edition: releasing the exercises of {len(notebooks)} notebooks (nbgrader)")
            shown, downloads = student_notebooks(notebooks, Path(tmp, "student"))
        else:
            shown, downloads = list(notebooks), {nb.name: nb for nb in notebooks}
        landing, figure = landing_page(readme, notebooks, edition, log)
        stage(project, shown, docs, readme, landing, figure)
        log(f"book: jupyter-book build --site ({len(notebooks)} notebooks, {len(docs)} docs)")
        site_dir = run_myst(project)
        katex_dir, why = None, ""
        if katex:
            tgz, why = fetch_katex(katex_cache())
            if tgz is not None:
                katex_dir = extract_katex(tgz, Path(tmp, "katex"))
        if katex_dir is None:
            log(f"book: KaTeX's style sheet is not at hand ({why or 'not asked for'}); the equations are "
                "drawn by the browser's MathML instead")
        released = frozenset(name for name, src in downloads.items() if src not in notebooks)
        summary = _render(new, site_dir, shown, downloads, katex_dir, edition, released)
    return {**summary, "katex": katex_dir is not None, "notebooks": [nb.name for nb in notebooks],
            "edition": edition, "key_figure": figure is not None}


def _render(new: Path, site_dir: Path, shown: list[Path], downloads: dict[str, Path], katex_dir: Path | None,
            edition: str, released: frozenset[str] = frozenset()) -> dict:
    """Render MyST's content in ``site_dir`` into ``new``, with each lesson's notebook to download."""
    modules = index_package()
    lesson_names, lesson_pages, slug_files = {}, {}, {}
    for nb in shown:
        slug = _slug_for(site_dir, nb.name)
        lesson_pages[nb.name] = f"{slug}.html"
        slug_files[slug] = nb.name
        data = json.loads(nb.read_text(encoding="utf-8"))
        sources = ["".join(c.get("source", "")) for c in data.get("cells", []) if c.get("cell_type") == "code"]
        lesson_names[slug] = notebook_names(sources, modules)
    utils.make_dir(new)
    site = Site(site_dir, new, modules, lesson_names, katex_dir is not None, slug_files, edition, released)
    site.write_static(katex_dir)
    pages = site.render_pages()
    sources = site.render_sources()
    utils.make_dir(new / "notebooks")
    for name, src in downloads.items():
        copy_file(src, new / "notebooks" / name)
    search_bytes = site.write_search_index()
    write_file(new / ".nojekyll", "")
    return {"pages": pages, "source_pages": len(sources), "figures": len(site.images), "lesson_pages": lesson_pages,
            "downloads": {name: f"notebooks/{name}" for name in downloads}, "search_index_bytes": search_bytes}


def _slug_for(site_dir: Path, filename: str) -> str:
    """The page slug MyST gave the notebook ``filename`` (by each page's ``location``)."""
    for path in sorted((site_dir / "content").glob("*.json")):
        if path.stat().st_size <= MAX_PAGE_JSON_BYTES:
            location = str(json.loads(path.read_text(encoding="utf-8")).get("location", ""))
            if location.endswith("/" + filename):
                return path.stem
    return ""


def add_arguments_book(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("site"),
                   help="folder for the web site (default: site); new, empty, or one this command wrote before "
                   "(it is replaced only when the new site is complete); never a folder of files git tracks")
    p.add_argument("--edition", choices=EDITIONS, default="lecturer",
                   help="lecturer (default): the executed lessons with their solutions folded, for the lecturer and "
                   "a reader; student: the same lessons and outputs without any solution, solution output or "
                   "hidden test, each lesson linking its student notebook: the book to publish to a class")
    p.add_argument("--no-katex", action="store_true",
                   help="do not fetch KaTeX's style sheet and fonts from npm: equations are drawn by the "
                   "browser's MathML")


def run_book(args) -> int:
    summary = build(args.out, katex=not args.no_katex, edition=getattr(args, "edition", "lecturer"))
    print(f"book ({summary['edition']} edition): {len(summary['pages'])} pages ({len(summary['notebooks'])} "
          f"lessons), {summary['source_pages']} source pages, {summary['figures']} figures, in {args.out}")
    print(f"book: read it with a static server, e.g. python -m http.server -d {args.out} 8000, then open "
          "http://localhost:8000/")
    return 0

