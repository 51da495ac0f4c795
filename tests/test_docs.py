"""The documentation's links hold: every relative link in the README and under ``docs/`` names a
file that exists, and every ``#anchor`` a heading of its target (GitHub's slugs). The README stays
a front door of at most 300 lines."""

from __future__ import annotations

import re
from pathlib import Path
from urllib.parse import unquote

import pytest

REPO = Path(__file__).resolve().parents[1]
README_MAX_LINES = 300

_FENCE = re.compile(r"^ {0,3}(`{3,}|~{3,})")
_HEADING = re.compile(r"^ {0,3}(#{1,6})\s+(.*?)\s*#*\s*$")
_CODE_SPAN = re.compile(r"(`+)(.+?)\1", re.S)
_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\[\]]*\])*\]\(\s*<?([^)\s>]*)>?(?:\s+(?:\"[^\"]*\"|'[^']*'))?\s*\)")
_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:")


def doc_files(repo: Path = REPO) -> list[Path]:
    """README.md and every Markdown file under docs/."""
    return [repo / "README.md", *sorted((repo / "docs").rglob("*.md"))]


def slug(heading: str) -> str:
    """GitHub's anchor for a heading's text: inline markup dropped, lower case, punctuation other
    than ``-`` and ``_`` removed, each space a hyphen."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link in a heading keeps its text
    text = re.sub(r"<[^>]+>", "", text).replace("`", "").replace("*", "")
    text = "".join(c for c in text.lower() if c.isalnum() or c in " -_")
    return text.replace(" ", "-")


def _prose(text: str) -> tuple[list[str], list[str]]:
    """``(headings, paragraphs)`` of a Markdown text outside fenced code blocks."""
    headings: list[str] = []
    paragraphs: list[str] = []
    block: list[str] = []
    fence: str | None = None
    for line in text.splitlines():
        opened = _FENCE.match(line)
        if fence is not None:
            if opened and opened.group(1)[0] == fence[0] and len(opened.group(1)) >= len(fence):
                fence = None
            continue
        if opened:
            fence = opened.group(1)
            paragraphs.append("\n".join(block))
            block = []
            continue
        heading = _HEADING.match(line)
        if heading:
            headings.append(heading.group(2))
        if line.strip():
            block.append(line)
        else:
            paragraphs.append("\n".join(block))
            block = []
    paragraphs.append("\n".join(block))
    return headings, [p for p in paragraphs if p]


def anchors(path: Path) -> set[str]:
    """Every anchor GitHub makes for the headings of a Markdown file (repeats get -1, -2, ...)."""
    seen: dict[str, int] = {}
    out: set[str] = set()
    for heading in _prose(path.read_text(encoding="utf-8"))[0]:
        base = slug(heading)
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def links(path: Path) -> list[str]:
    """The link targets of a Markdown file, code blocks and code spans left out."""
    found: list[str] = []
    for paragraph in _prose(path.read_text(encoding="utf-8"))[1]:
        found += [m.group(1) for m in _LINK.finditer(_CODE_SPAN.sub("", paragraph))]
    return found


def broken_links(path: Path, repo: Path = REPO) -> list[str]:
    """What is wrong with each relative link of ``path``: a missing file, or an anchor that is no
    heading of its Markdown target. Web and mail links are not checked."""
    problems: list[str] = []
    for target in links(path):
        if not target or _SCHEME.match(target):
            continue
        file_part, _, anchor = target.partition("#")
        dest = (path.parent / unquote(file_part)).resolve() if file_part else path
        where = f"{path.relative_to(repo)}: ({target})"
        if not dest.exists():
            problems.append(f"{where}: {file_part} does not exist")
        elif anchor and dest.suffix == ".md" and unquote(anchor) not in anchors(dest):
            problems.append(f"{where}: no heading #{anchor} in {dest.relative_to(repo)}")
    return problems


def test_the_readme_is_a_front_door():
    lines = (REPO / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, (
        f"README.md has {len(lines)} lines (at most {README_MAX_LINES}): guides, reference and dated "
        "results belong in docs/")


def test_there_is_a_documentation_tree():
    files = doc_files()
    assert REPO / "docs" / "README.md" in files and REPO / "docs" / "results" / "README.md" in files
    assert sum(target.startswith("docs/") for target in links(REPO / "README.md")) >= 10, "the README links into docs/"


@pytest.mark.parametrize("path", doc_files(), ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_resolves(path):
    problems = broken_links(path)
    assert not problems, "broken links:\n" + "\n".join(problems)


def test_github_slugs():
    assert slug("Installing in a real home") == "installing-in-a-real-home"
    assert slug("Keeping cameras calibrated: the moved-camera alarm") == "keeping-cameras-calibrated-the-moved-camera-alarm"
    assert slug("Fitting the whole board: --fit-board") == "fitting-the-whole-board---fit-board"
    assert slug("[view] and [notify]") == "view-and-notify"
    assert slug("`common/` (the kernel)") == "common-the-kernel"
    assert slug("python -m evaluation.moved_suite") == "python--m-evaluationmoved_suite"
    assert slug("Privacy: what leaves a [camera](x.md) host") == "privacy-what-leaves-a-camera-host"


def test_a_broken_link_or_anchor_is_found(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "a.md").write_text("# A\n\n## Same\n\n## Same\n\ntext\n", encoding="utf-8")
    page = tmp_path / "README.md"
    page.write_text(
        "# Top\n\n"
        "[fine](docs/a.md), [anchor](docs/a.md#same-1), [here](#top), [web](https://example.org/x), "
        "[mail](mailto:a@example.org), `[in code](missing.md)`\n\n"
        "```\n[in a block](missing.md)\n```\n\n"
        "[gone](docs/missing.md) and ![picture](docs/missing.png) and [bad anchor](docs/a.md#nowhere) "
        "and [bad here](#nowhere)\n",
        encoding="utf-8")
    problems = broken_links(page, repo=tmp_path)
    assert len(problems) == 4, problems
    assert any("docs/missing.md does not exist" in p for p in problems)
    assert any("docs/missing.png does not exist" in p for p in problems)
    assert any("no heading #nowhere in docs/a.md" in p for p in problems)
    assert any("no heading #nowhere in README.md" in p for p in problems)


_DOC_PATH = re.compile(r"\b(?:README\.md|docs/[\w./-]+?\.md)\b")
_CODE_SUFFIXES = {".py", ".toml", ".service", ".js", ".html", ".sh"}


def code_pointers(repo: Path = REPO) -> list[tuple[str, str]]:
    """``(file, pointer)`` for every ``docs/....md`` a code, configuration or deployment file names
    that does not exist (``README.md`` itself always does)."""
    missing = []
    for path in sorted(repo.rglob("*")):
        rel = path.relative_to(repo)
        if path.suffix not in _CODE_SUFFIXES or rel.parts[0] in {".venv", ".git", "build", "docs"} or \
                rel == Path("tests/test_docs.py") or not path.is_file():   # this file's examples are made up
            continue
        for found in _DOC_PATH.findall(path.read_text(errors="replace")):
            if not (repo / found).is_file():
                missing.append((str(rel), found))
    return missing


def test_the_documents_code_points_to_exist():
    """Comments, help texts and unit files send readers to pages of docs/: each page is there."""
    assert code_pointers() == []


def test_a_pointer_to_a_missing_page_is_found(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "here.md").write_text("# Here\n")
    (tmp_path / "run.py").write_text('"""See docs/here.md and docs/gone.md."""\n')
    assert code_pointers(tmp_path) == [("run.py", "docs/gone.md")]


COMMANDS_PAGE = REPO / "docs" / "reference" / "commands.md"
_USAGE_BLOCK = re.compile(r"^```\n(usage: .*?)^```$", re.S | re.M)


def _command_of(usage: str) -> list[str]:
    """The command words of a usage line: ``usage: voxelwatch calibrate floor [-h] ...`` ->
    ``["voxelwatch", "calibrate", "floor"]``."""
    line = usage.split("\n", 1)[0].split()[1:]
    if line[:2] == ["python", "-m"]:
        return line[:3]
    words = []
    for word in line:
        if word.startswith(("[", "-", "{")) or word.isupper():
            break
        words.append(word)
    return words


def help_text(command: list[str]) -> str:
    """The ``--help`` of a documented command, as an 80-column terminal shows it (run in this
    process: each command's ``main`` prints its help and exits)."""
    import contextlib
    import importlib
    import io
    import os

    if command[:2] == ["python", "-m"]:
        main, argv = importlib.import_module(command[2]).main, command[3:]
    elif command[0] == "voxelwatch-camera":
        main, argv = importlib.import_module("camera_worker.cli").main, command[1:]
    elif command[0] == "voxelwatch-fusion":
        main, argv = importlib.import_module("fusion_server.cli").main, command[1:]
    else:
        assert command[0] == "voxelwatch", command
        main, argv = importlib.import_module("voxelwatch.cli").main, command[1:]
    out = io.StringIO()
    columns = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "80"
    try:
        with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
            main([*argv, "--help"])
    finally:
        if columns is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = columns
    return out.getvalue()


def commands_page(text: str) -> str:
    """The commands page with every usage block replaced by its command's help today."""
    return _USAGE_BLOCK.sub(lambda m: "```\n" + help_text(_command_of(m.group(1))).rstrip("\n") + "\n```", text)


def test_the_commands_page_shows_each_commands_help_as_it_is():
    """docs/reference/commands.md quotes every command's --help; a flag added, renamed or given new
    bounds shows there (rewrite the page with ``python tests/test_docs.py``)."""
    text = COMMANDS_PAGE.read_text()
    documented = {" ".join(_command_of(block)[:2]) for block in _USAGE_BLOCK.findall(text)}
    subcommands = re.findall(r"^    (\w+) ", help_text(["voxelwatch"]), re.M)
    assert len(subcommands) >= 14, subcommands
    named = {"camera": "voxelwatch-camera", "fusion": "voxelwatch-fusion"}
    assert {named.get(c, f"voxelwatch {c}") for c in subcommands} <= documented, documented
    assert commands_page(text) == text, "the commands page is stale: run python tests/test_docs.py"


if __name__ == "__main__":
    import sys

    sys.path.insert(0, str(REPO))
    COMMANDS_PAGE.write_text(commands_page(COMMANDS_PAGE.read_text()))
    print(f"wrote {COMMANDS_PAGE.relative_to(REPO)}")
