"""The README and docs as a new user meets them: every Python block runs as pasted, every
``fastmem`` command of the README runs, and every reference points to a file that ships."""

from __future__ import annotations

import argparse
import importlib.util
import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
DOCS = ROOT / "docs"

if not README.is_file():  # pragma: no cover - tests run from an installed package only
    pytest.skip("README.md not found next to the tests", allow_module_level=True)

#: A fenced block preceded by this comment is not run (it needs files the reader has).
NOT_RUNNABLE = "<!-- not runnable as pasted -->"


def _blocks(path: Path, language: str) -> list[tuple[int, str]]:
    """(line number, code) of every fenced block of ``language`` that is meant to run."""
    lines = path.read_text(encoding="utf-8").splitlines()
    out, i = [], 0
    while i < len(lines):
        if lines[i].strip() == f"```{language}":
            start = i + 1
            j = start
            while lines[j].strip() != "```":
                j += 1
            previous = lines[i - 1].strip() if i else ""
            if previous != NOT_RUNNABLE:
                out.append((start + 1, "\n".join(lines[start:j]) + "\n"))
            i = j
        i += 1
    return out


PYTHON_BLOCKS = _blocks(README, "python")


def test_readme_has_python_blocks_and_few_exceptions():
    assert len(PYTHON_BLOCKS) >= 2
    assert README.read_text(encoding="utf-8").count(NOT_RUNNABLE) <= 2


@pytest.mark.parametrize(
    ("line", "code"), PYTHON_BLOCKS, ids=[f"line{n}" for n, _ in PYTHON_BLOCKS]
)
def test_readme_python_block_runs_as_pasted(line, code, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    exec(compile(code, f"README.md:{line}", "exec"), {"__name__": "__readme__"})
    capsys.readouterr()


def _cli_commands() -> list[list[str]]:
    commands = []
    for _, code in _blocks(README, "bash"):
        for raw in code.splitlines():
            words = shlex.split(raw, comments=True)
            if words[:1] == ["fastmem"]:
                commands.append(words[1:])
    return commands


def _run_in_order(commands, tmp_path, monkeypatch, capsys) -> int:
    """Run ``fastmem`` command lines in order in one folder; return how many ran."""
    from fastmem.cli.main import main

    monkeypatch.chdir(tmp_path)
    has_plot = importlib.util.find_spec("matplotlib") is not None
    has_dask = all(importlib.util.find_spec(m) for m in ("dask", "distributed", "pandas"))
    ran = 0
    for argv in commands:
        if (argv[0] == "plot" or argv[:2] == ["twophase", "plot"]) and not has_plot:
            continue
        if argv[0] == "sweep" and not has_dask:
            continue
        if argv[0] == "sweep" and not (tmp_path / argv[-1]).exists():
            continue  # a study file the reader writes; docs/sweeps.md has one to run
        if argv[0] == "plot" and "--x" in argv and not (tmp_path / argv[1]).exists():
            continue  # the plot of that study (tests/sweeps/test_sweep.py runs one)
        assert main(argv) == 0, argv
        ran += 1
    assert "error:" not in capsys.readouterr().err
    return ran


def _is_twophase(argv) -> bool:
    return argv[0] == "twophase" or (argv[0] == "info" and argv[1].startswith("twophase"))


def test_readme_cli_commands_run_in_order(tmp_path, monkeypatch, capsys):
    """The README's ``fastmem ...`` lines of the contact problem, in order, in one folder,
    but its figures (``fastmem plot``: tests/cli/test_plot.py draws them; the next test,
    a slow one, runs every line, figures and two-phase runs included)."""
    commands = [a for a in _cli_commands() if not _is_twophase(a) and a[0] != "plot"]
    assert len(commands) >= 5
    assert _run_in_order(commands, tmp_path, monkeypatch, capsys) >= 5


def test_readme_every_cli_command_runs_in_order(tmp_path, monkeypatch, capsys):
    """Every ``fastmem ...`` line of the README's shell blocks, in order, in one folder
    (about 20 s: slow)."""
    commands = _cli_commands()
    assert len(commands) >= 12
    assert _run_in_order(commands, tmp_path, monkeypatch, capsys) >= 10


_LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")


@pytest.mark.parametrize("doc", [README, *sorted(DOCS.glob("*.md"))], ids=lambda p: p.name)
def test_markdown_links_point_to_files_that_exist(doc):
    for target in _LINK.findall(doc.read_text(encoding="utf-8")):
        if "://" in target:
            continue
        assert (doc.parent / target).exists(), f"{doc.name} links to missing {target}"


def test_no_reference_to_files_that_do_not_ship():
    """Docstrings, help texts and docs cite docs/method.md, not the design notes."""
    bad = re.compile(r"MATH\.md|ARCHITECTURE\.md|BENCHMARKS\.md|shared/design")
    offenders = []
    for folder in ("fastmem", "kernels", "bench", "docs", "examples"):
        for path in (ROOT / folder).rglob("*"):
            if path.suffix in (".py", ".md") and bad.search(path.read_text(encoding="utf-8")):
                offenders.append(str(path.relative_to(ROOT)))
    if bad.search(README.read_text(encoding="utf-8")):
        offenders.append("README.md")
    assert offenders == []


def _run_options() -> set[str]:
    from fastmem.cli.main import _build_parser

    parser = _build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    options = set()
    for name, command in sub.choices.items():
        options.add(name)
        for action in command._actions:
            options.update(o for o in action.option_strings if o.startswith("--"))
    return options - {"--help"}


def test_cli_doc_covers_every_command_and_option():
    text = (DOCS / "cli.md").read_text(encoding="utf-8")
    missing = sorted(o for o in _run_options() if f"`{o}" not in text)
    assert missing == []


def test_archive_doc_covers_every_dataset():
    from fastmem.io.schema import DATASETS, GROUPS

    text = (DOCS / "archive.md").read_text(encoding="utf-8")
    missing = [g for g in GROUPS if f"`/{g}`" not in text]
    missing += [p for p in DATASETS if f"`{p.split('/')[-1]}`" not in text]
    assert missing == []


def test_performance_section_holds_only_the_template():
    """The generated section of docs/performance.md has the template's bullets and no
    others: measurements written by hand go after it (``bench.report --write`` replaces
    the whole section, so a hand-written bullet inside it would be lost)."""

    def bullets(text):
        body = text.split("<!-- begin section -->", 1)[1].split("<!-- end section -->", 1)[0]
        return re.findall(r"^- \*\*([^*]+)\*\*", body, flags=re.M)

    template = (ROOT / "bench" / "PERFORMANCE.md").read_text(encoding="utf-8")
    page = (DOCS / "performance.md").read_text(encoding="utf-8")
    assert bullets(template)  # the markers and bullets are there to compare
    assert bullets(page) == bullets(template)
    assert "## Issue 33, session by session" in page.split("<!-- end section -->", 1)[1]
