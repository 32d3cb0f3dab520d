"""What the web book (:mod:`geodepth_lite.workbook.book`) gives its reader besides the pages: printed Markdown
tables drawn as tables, the "on this page" list, the search index and the script that searches it
and opens the sidebar on a narrow screen, and the landing page.

Nothing here runs a notebook or changes one: a printed table is converted from the text the notebook
stored, at build time; the search runs in the reader's browser over an index written at build time
(a script file, so that it loads from ``file://`` as well as from a static server), with no network.
"""

from __future__ import annotations

import base64
import html
import html.parser
import json
import re

# --------------------------------------------------------------------------- printed Markdown tables

PIPE_ROW = re.compile(r"^\s*\|.*\|\s*$")
SEPARATOR_CELL = re.compile(r"^:?-+:?$")


def pipe_cells(line: str) -> list[str]:
    """The cells of one table row ``| a | b |`` (outer pipes dropped, ``\\|`` kept as a pipe), stripped."""
    inner = line.strip()[1:-1]
    cells, cur, i = [], [], 0
    while i < len(inner):
        if inner[i] == "\\" and inner[i + 1:i + 2] == "|":
            cur.append("|")
            i += 2
            continue
        if inner[i] == "|":
            cells.append("".join(cur).strip())
            cur = []
        else:
            cur.append(inner[i])
        i += 1
    cells.append("".join(cur).strip())
    return cells


def _cell_html(text: str) -> str:
    """A cell's text escaped, with the two marks the printed tables use: ``**bold**`` and ```code```."""
    out = html.escape(text, quote=False)
    out = re.sub(r"`([^`]+)`", r"<code>\1</code>", out)
    return re.sub(r"\*\*(.+?)\*\*", r"<strong>\1</strong>", out)


def pipe_table(lines: list[str]) -> str | None:
    """The HTML ``<table>`` of a well-formed pipe table (a header row, a separator row of dashes with
    optional colons, body rows with as many cells as the header), or None for anything else."""
    if len(lines) < 2 or not all(PIPE_ROW.match(ln) for ln in lines):
        return None
    rows = [pipe_cells(ln) for ln in lines]
    head, sep, body = rows[0], rows[1], rows[2:]
    if len(sep) != len(head) or not all(SEPARATOR_CELL.match(c) for c in sep):
        return None
    if any(len(r) != len(head) for r in body):
        return None
    aligns = []
    for c in sep:
        side = {(True, True): "center", (True, False): "left", (False, True): "right"}.get(
            (c.startswith(":"), c.endswith(":")))
        aligns.append(f' style="text-align:{side}"' if side else "")
    th = "".join(f"<th{a}>{_cell_html(c)}</th>" for a, c in zip(aligns, head))
    trs = "".join("<tr>" + "".join(f"<td{a}>{_cell_html(c)}</td>" for a, c in zip(aligns, r)) + "</tr>"
                  for r in body)
    return f'<table class="printed"><thead><tr>{th}</tr></thead><tbody>{trs}</tbody></table>'


def text_blocks(text: str) -> list[tuple[str, str]]:
    """A printed text split into ``("text", str)`` and ``("table", html)`` blocks: each run of lines
    that start and end with ``|`` becomes a table where it is a well-formed pipe table
    (:func:`pipe_table`) and stays text otherwise."""
    blocks: list[tuple[str, str]] = []
    lines = text.split("\n")
    i = 0
    while i < len(lines):
        j = i
        is_row = bool(PIPE_ROW.match(lines[i]))
        while j < len(lines) and bool(PIPE_ROW.match(lines[j])) == is_row:
            j += 1
        run = lines[i:j]
        table = pipe_table(run) if is_row else None
        if table is not None:
            blocks.append(("table", table))
        elif blocks and blocks[-1][0] == "text":
            blocks[-1] = ("text", blocks[-1][1] + "\n" + "\n".join(run))
        else:
            blocks.append(("text", "\n".join(run)))
        i = j
    return blocks


def printed_html(text: str, cls: str = "") -> str:
    """Printed output as HTML: its pipe tables as tables, everything else preformatted text, escaped."""
    attr = f' class="{cls}"' if cls else ""
    blocks = text_blocks(text)
    if not any(kind == "table" for kind, _ in blocks):
        return f"<pre{attr}>{html.escape(text, quote=False)}</pre>"
    parts = []
    for kind, value in blocks:
        if kind == "table":
            parts.append(f'<div class="printed-table">{value}</div>')
        elif value.strip():
            parts.append(f"<pre{attr}>{html.escape(value.strip(chr(10)), quote=False)}</pre>")
    return "".join(parts)


# --------------------------------------------------------------------------- "on this page"


def page_toc(headings: list[tuple[int, str, str]]) -> str:
    """The page's headings of depth 2 and 3 (``(depth, id, text)``) as a list of links; "" for fewer than two."""
    items = [(d, hid, text) for d, hid, text in headings if d in (2, 3) and hid]
    if len(items) < 2:
        return ""
    lis = "".join(f'<li class="d{d}"><a href="#{html.escape(hid)}">{html.escape(text)}</a></li>'
                  for d, hid, text in items)
    return ('<nav class="page-toc" aria-label="On this page"><p class="page-toc-title">On this page</p>'
            f"<ul>{lis}</ul></nav>")


def strip_tags(fragment: str) -> str:
    """The text of an HTML fragment the book wrote (tags dropped, entities read)."""
    return html.unescape(re.sub(r"<[^>]+>", "", fragment))


# --------------------------------------------------------------------------- the search index

VOID = frozenset("area base br col embed hr img input link meta source track wbr".split())
SKIPPED = frozenset("pre script style iframe details nav svg button form".split())  # code, outputs, folds


class _Sections(html.parser.HTMLParser):
    """A page's prose by section: a new section at each ``h1``-``h3`` with an id; code, outputs, folded
    solutions, navigation and typeset math (KaTeX's markup) are left out."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.sections: list[list] = [["", "", []]]  # [id, heading, texts]
        self.skip = 0  # depth inside a skipped element
        self.heading: list[str] | None = None

    def handle_starttag(self, tag, attrs):
        if tag in VOID:
            return
        if self.skip:
            self.skip += 1
            return
        a = dict(attrs)
        if tag in SKIPPED or "katex" in (a.get("class") or "") or "geodepth-3d" in (a.get("class") or ""):
            self.skip = 1
        elif tag in ("h1", "h2", "h3") and a.get("id"):
            self.sections.append([a["id"], "", []])
            self.heading = []

    def handle_endtag(self, tag):
        if tag in VOID:
            return
        if self.skip:
            self.skip -= 1
        elif tag in ("h1", "h2", "h3") and self.heading is not None:
            self.sections[-1][1] = " ".join("".join(self.heading).split())
            self.heading = None

    def handle_data(self, data):
        if self.skip:
            return
        (self.heading if self.heading is not None else self.sections[-1][2]).append(data)


def page_sections(body: str) -> list[list[str]]:
    """``[[id, heading, text], ...]`` of a page's HTML body, for the search index (empty sections dropped)."""
    parser = _Sections()
    # code and scripts first, whole (the book escapes their text, so neither holds its own end tag): much faster
    parser.feed(re.sub(r"<(pre|script)\b.*?</\1>", " ", body, flags=re.S))
    parser.close()
    out = []
    for hid, heading, texts in parser.sections:
        text = " ".join(" ".join(texts).split())
        if heading or text:
            out.append([hid, heading, text])
    return out


INDEX_GLOBAL = "geodepthSearchIndex"


def search_index_js(pages: list[dict]) -> str:
    """The search index as a script: ``window.geodepthSearchIndex = {"pages": [{"t": title, "u": url,
    "s": [[id, heading, text], ...]}, ...]};`` (a script, not a .json file: it loads from file:// too)."""
    data = json.dumps({"pages": pages}, ensure_ascii=False, separators=(",", ":"))
    return f"window.{INDEX_GLOBAL} = {data};\n"


def read_search_index(text: str) -> dict:
    """The index back from :func:`search_index_js`'s script (for checks)."""
    prefix = f"window.{INDEX_GLOBAL} = "
    if not text.startswith(prefix):
        raise ValueError("not a search index script")
    return json.loads(text[len(prefix):].rstrip().rstrip(";"))


BOOK_JS = """(function () {
  "use strict";
  var root = document.body.getAttribute("data-root") || "";
  var button = document.querySelector(".menu-toggle");
  if (button) {
    button.addEventListener("click", function () {
      var open = document.body.classList.toggle("nav-open");
      button.setAttribute("aria-expanded", open ? "true" : "false");
    });
  }
  var input = document.getElementById("search-input");
  var list = document.getElementById("search-results");
  if (!input || !list) { return; }
  var waiting = null;
  function withIndex(done) {
    if (window.%(index)s) { done(); return; }
    if (waiting === null) {
      waiting = [];
      var script = document.createElement("script");
      script.src = root + "_static/search-index.js";
      script.onload = function () { waiting.forEach(function (f) { f(); }); };
      document.head.appendChild(script);
    }
    waiting.push(done);
  }
  function item(href, title, snippet) {
    var li = document.createElement("li");
    var a = document.createElement(href ? "a" : "span");
    if (href) { a.href = href; }
    a.textContent = title;
    li.appendChild(a);
    if (snippet) {
      var s = document.createElement("span");
      s.className = "snippet";
      s.textContent = snippet;
      li.appendChild(s);
    }
    return li;
  }
  function search() {
    var q = input.value.trim().toLowerCase();
    list.textContent = "";
    if (q.length < 2) { return; }
    var terms = q.split(/\\s+/);
    var hits = [];
    window.%(index)s.pages.forEach(function (page, p) {
      page.s.forEach(function (sec, k) {
        var head = (page.t + " " + sec[1]).toLowerCase();
        var hay = head + " " + sec[2].toLowerCase();
        if (!terms.every(function (t) { return hay.indexOf(t) >= 0; })) { return; }
        var score = terms.reduce(function (n, t) { return n + (head.indexOf(t) >= 0 ? 10 : 1); }, 0);
        hits.push({page: page, sec: sec, score: score, order: p * 10000 + k});
      });
    });
    hits.sort(function (a, b) { return b.score - a.score || a.order - b.order; });
    if (!hits.length) {
      list.appendChild(item("", "Nothing found", ""));
      return;
    }
    hits.slice(0, 25).forEach(function (h) {
      var text = h.sec[2], at = text.toLowerCase().indexOf(terms[0]);
      var snippet = at < 0 ? text.slice(0, 120) : (at > 50 ? "..." : "") + text.slice(Math.max(0, at - 50), at + 90);
      var title = h.sec[1] && h.sec[1] !== h.page.t ? h.page.t + " \\u203a " + h.sec[1] : h.page.t;
      list.appendChild(item(root + h.page.u + (h.sec[0] ? "#" + h.sec[0] : ""), title, snippet));
    });
  }
  input.form && input.form.addEventListener("submit", function (e) {
    e.preventDefault();
    var first = list.querySelector("a[href]");
    if (first) { window.location.href = first.href; }
  });
  input.addEventListener("focus", function () { withIndex(function () {}); });
  input.addEventListener("input", function () { withIndex(search); });
})();
""" % {"index": INDEX_GLOBAL}


# --------------------------------------------------------------------------- the landing page

KEY_FIGURE = re.compile(r"\*\*The key figure\*\*[^:]*:\s*(\[[^\]]*\]\((notebooks/[\w.-]+\.ipynb)\),\s*section\s*"
                        r"\"([^\"]+)\".*)", re.S)


def readme_purpose(readme: str) -> list[str]:
    """The README's opening paragraphs (before its key figure or its first section): the project's purpose."""
    paras = [p.strip() for p in re.split(r"\n\s*\n", readme) if p.strip()]
    out = []
    for p in paras:
        if p.startswith("# ") and not out:
            continue
        if p.startswith(("#", "**The key figure**")):
            break
        out.append(p)
    return out


def key_figure_ref(readme: str) -> tuple[str, str, str] | None:
    """(notebook file name, section title, caption) of the figure the README calls the key figure."""
    for p in re.split(r"\n\s*\n", readme):
        m = KEY_FIGURE.match(p.strip())
        if m:
            return m.group(2).split("/")[-1], m.group(3), " ".join(m.group(1).split())
    return None


def section_figure(nb: dict, section: str) -> bytes | None:
    """The first PNG figure the code cells of a notebook's section (from its heading to the next
    heading of the same or a higher level) drew."""
    level = None
    for cell in nb.get("cells", []):
        src = "".join(cell.get("source", ""))
        if cell.get("cell_type") == "markdown":
            for line in src.splitlines():
                m = re.match(r"^(#+)\s+(.*?)\s*$", line)
                if m and level is None and m.group(2) == section:
                    level = len(m.group(1))
                elif m and level is not None and len(m.group(1)) <= level:
                    return None
            continue
        if level is None:
            continue
        for out in cell.get("outputs", []):
            png = (out.get("data") or {}).get("image/png")
            if png:
                return base64.b64decode("".join(png) if isinstance(png, list) else png)
    return None


def first_heading(nb: dict) -> str:
    for cell in nb.get("cells", []):
        if cell.get("cell_type") == "markdown":
            for line in "".join(cell.get("source", "")).splitlines():
                if line.startswith("# "):
                    return line[2:].strip()
    return ""


def landing_markdown(purpose: list[str], lessons: list[tuple[str, str]], figure: tuple[str, str] | None,
                     student: bool) -> str:
    """The book's own landing page (MyST markdown): the purpose, the key figure (``(file, caption)``), the
    lessons (``(notebook file, title)``) and how to run them."""
    lines = ["---", "title: geodepth-lite", "---", ""]
    lines += [p + "\n" for p in (purpose or ["The lessons of the workbook, in order."])]
    if figure:
        lines += ["## The key figure", "", f"![The key figure]({figure[0]})", "", figure[1], ""]
    lines += ["## The lessons", ""]
    lines += [f"{k + 1}. [{title or name}](notebooks/{name})" for k, (name, title) in enumerate(lessons)]
    lines += ["", "## Run the notebooks", ""]
    if student:
        lines += ["Each lesson page links its notebook as you get it in a class: the exercises to solve, outputs "
                  "cleared. Your lecturer hands out the student edition of the project; inside it:", ""]
        run = ["python -m pip install -r environment.txt",
               "python -m geodepth_lite unbundle teach-models.zip   # the trained models your lecturer hands out",
               "jupyter lab notebooks/"]
    else:
        lines += ["Each lesson page links its executed notebook. To run the lessons yourself, from a checkout of "
                  "the project (Python 3.10 or newer):", ""]
        run = ["python -m pip install -r environment.txt",
               "python -m geodepth_lite reproduce   # trains the models the notebooks load (the README gives times)",
               "jupyter lab notebooks/"]
    lines += ["```bash", *run, "```", ""]
    if not student:
        lines += ["In a class, `python -m geodepth_lite unbundle teach-models.zip` replaces `reproduce`, and students "
                  "get the student edition, without solutions.", ""]
    return "\n".join(lines)
