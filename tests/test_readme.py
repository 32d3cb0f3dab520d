"""The README stays an entry page: short, the two commands CI runs, no lab journal, no machine paths,
and every relative link in it and in docs/ leads to a file that exists."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
MAX_README_LINES = 300
COMMANDS = (
    "python -m pip install -r environment.txt && python -m geodepth_lite reproduce",
    "python -m pytest",
)
# history and this machine's paths do not belong in user-facing text
FORBIDDEN = ("earlier machine", "/work/", "/tmp/")

FENCE = re.compile(r"^(```|~~~).*?^\1[ \t]*$", re.MULTILINE | re.DOTALL)
INLINE_CODE = re.compile(r"`[^`\n]*`")
LINK = re.compile(r"\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")


def markdown_pages() -> list[Path]:
    pages = [README, *sorted((ROOT / "docs").glob("*.md"))]
    changelog = ROOT / "CHANGELOG.md"
    return pages + [changelog] if changelog.exists() else pages


def bash_blocks(text: str) -> list[str]:
    """The bodies of the ```bash fenced blocks of a markdown text."""
    return re.findall(r"^```bash[ \t]*\n(.*?)^```[ \t]*$", text, re.MULTILINE | re.DOTALL)


def broken_links(text: str, base: Path) -> list[str]:
    """Relative links `](target)` of a markdown text (outside code) whose file does not exist under base.

    Links to web addresses (http, https, mailto) and to anchors of the same page (#...) are not
    checked; an #anchor after a file name is dropped before the file is looked up.
    """
    prose = INLINE_CODE.sub("", FENCE.sub("", text))
    broken = []
    for target in LINK.findall(prose):
        if target.startswith(("http://", "https://", "mailto:", "#")):
            continue
        path = target.split("#", 1)[0]
        if not path or not (base / path).is_file():
            broken.append(target)
    return broken


def test_readme_is_short():
    n = len(README.read_text(encoding="utf-8").splitlines())
    assert n <= MAX_README_LINES, f"README.md has {n} lines; at most {MAX_README_LINES}"


def test_readme_has_the_two_commands_in_a_bash_block():
    blocks = bash_blocks(README.read_text(encoding="utf-8"))
    assert blocks, "README.md has no ```bash block"
    for command in COMMANDS:
        assert any(command in block.splitlines() for block in blocks), (
            f"README.md: no ```bash block holds the line {command!r}")


@pytest.mark.parametrize("page", markdown_pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_history_or_machine_paths(page):
    text = page.read_text(encoding="utf-8")
    found = [s for s in FORBIDDEN if s.lower() in text.lower()]
    assert not found, f"{page.relative_to(ROOT)} mentions {found}"


@pytest.mark.parametrize("page", [README, *sorted((ROOT / "docs").glob("*.md"))],
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_point_to_existing_files(page):
    broken = broken_links(page.read_text(encoding="utf-8"), page.parent)
    assert not broken, f"{page.relative_to(ROOT)}: links to missing files: {broken}"


def test_link_checker_catches_a_broken_link(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "here.md").write_text("# here\n")
    text = ("See [a page](docs/here.md), [a section](docs/here.md#here), [the web](https://example.org),\n"
            "[this page](#top), and [a missing page](docs/missing.md#part).\n"
            "```bash\necho [not a link](docs/absent.md)\n```\n")
    assert broken_links(text, tmp_path) == ["docs/missing.md#part"]
    assert broken_links("[a folder](docs)", tmp_path) == ["docs"]


def test_bash_block_reader_sees_only_bash_blocks():
    text = "```\npython -m pytest\n```\n\n```bash\necho one\npython -m pytest\n```\n"
    assert bash_blocks(text) == ["echo one\npython -m pytest\n"]


LOCAL_PATH = re.compile(r"(?<![\w.])/(?:work|tmp|home|root|Users)/[\w.-]+")


def output_texts(nb_path: Path) -> list[str]:
    """The text of every output of a committed notebook (images left out)."""
    import json

    texts = []
    for cell in json.loads(nb_path.read_text(encoding="utf-8"))["cells"]:
        for out in cell.get("outputs", []):
            texts.append("".join(out.get("text", "")))
            texts += ["".join(v) for k, v in out.get("data", {}).items() if k.startswith("text/")]
    return texts


@pytest.mark.parametrize("nb_path", sorted((ROOT / "notebooks").glob("*.ipynb")), ids=lambda p: p.name)
def test_committed_notebook_outputs_hold_no_local_paths(nb_path):
    found = sorted({m for text in output_texts(nb_path) for m in LOCAL_PATH.findall(text)})
    assert not found, f"{nb_path.name} prints paths of the machine that executed it: {found[:3]}"


def test_local_path_check_can_fail():
    assert LOCAL_PATH.findall("PosixPath('/work/main/runs/teach/records/x.json')") == ["/work/main"]
    assert LOCAL_PATH.findall("runs/teach/records and 1/tmp ratio") == []
