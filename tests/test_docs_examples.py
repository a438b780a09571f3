"""Examples that cannot go stale: every command the README and the guide (docs/**/*.md) show
is run here, on a copy of the sample data in a temporary folder, and what it prints is
compared with what the page shows.

The convention, one for every page:

- a fenced ```console block holds `$ hamid ...` lines (a line ending in `\\` goes on), each
  followed by what the command prints, standard error and output together as a terminal
  shows them at 100 columns, compared line by line (trailing spaces aside); a line `...`
  stands for any number of lines left out;
- a fenced ```sh block is a script run as it is (bash, `set -euo pipefail`): it must end
  with status 0;
- a fenced ```python block is a script run as it is (this interpreter, this working tree): it
  must end with status 0;
- a ```text block shows a command that is not run here (it needs files that are not in the
  repository, or takes minutes), and says so beside it.

The blocks of one page run in order in one folder, so a later block may read what an
earlier one wrote. The outputs shown were made by running the commands
(`python tests/test_docs_examples.py PAGE.md` rewrites a page's console outputs from a new
run, keeping blocks that elide lines for review by hand)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
FENCE = re.compile(r"^(\s*)```(\S*).*$")
ELISION = "..."
# The README's commands run in every test run; the guide's, some 2 minutes of fits on a
# busy machine, are marked slow (run in CI, and by `-m slow`).
QUICK_PAGES = {"README.md"}


@dataclass(frozen=True)
class Block:
    """A fenced block of a page: its info string, first line number and lines (unindented)."""

    kind: str
    line: int
    lines: tuple[str, ...]


@dataclass(frozen=True)
class Shown:
    """One `$ command` of a console block and the output lines shown under it."""

    command: str
    output: tuple[str, ...]


def blocks(page: Path) -> list[Block]:
    """The fenced blocks of a Markdown page, in order."""
    found, opened, body, indent, kind = [], None, [], "", ""
    for number, line in enumerate(page.read_text().splitlines(), start=1):
        fence = FENCE.match(line)
        if opened is None and fence:
            opened, indent, kind, body = number, fence.group(1), fence.group(2), []
        elif opened is not None and line.strip() == "```":
            found.append(Block(kind, opened, tuple(body)))
            opened = None
        elif opened is not None:
            body.append(line[len(indent):] if line.startswith(indent) else line.lstrip())
    assert opened is None, f"{page}: the block opened on line {opened} is never closed"
    return found


def shown(block: Block) -> list[Shown]:
    """The commands of a console block with the outputs shown under them."""
    commands: list[Shown] = []
    command, output, going_on = None, [], False
    for line in block.lines:
        if going_on:
            command += "\n" + line
        elif line.startswith("$ "):
            if command is not None:
                commands.append(Shown(command, tuple(output)))
            command, output = line[2:], []
        else:
            assert command is not None, f"line {block.line}: output before any command"
            output.append(line)
        going_on = line.endswith("\\")
    if command is not None:
        commands.append(Shown(command, tuple(output)))
    return commands


def _environment(folder: Path) -> dict[str, str]:
    """A `hamid` on PATH that runs this working tree with this interpreter, 100 columns,
    and unbuffered output, so that standard output and error interleave as on a terminal."""
    bin_folder = folder / ".bin"
    bin_folder.mkdir(exist_ok=True)
    script = bin_folder / "hamid"
    script.write_text(f'#!/bin/sh\nexec "{sys.executable}" -c '
                      f'"from hamid.cli import main; main()" "$@"\n')
    script.chmod(0o755)
    paths = [str(ROOT), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
    return {**os.environ, "PATH": os.pathsep.join([str(bin_folder), os.environ["PATH"]]),
            "PYTHONPATH": os.pathsep.join(paths), "COLUMNS": "100",
            "PYTHONUNBUFFERED": "1"}


def run(script: str, folder: Path) -> subprocess.CompletedProcess:
    """Run `script` with bash in `folder`, standard error merged into standard output."""
    return subprocess.run(["bash", "-c", "set -euo pipefail\n" + script], cwd=folder,
                          env=_environment(folder), stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, text=True, timeout=600,
                          stdin=subprocess.DEVNULL)


def normal(lines: list[str] | tuple[str, ...]) -> list[str]:
    """Lines without trailing spaces, nor blank lines at either end."""
    lines = [line.rstrip() for line in lines]
    while lines and not lines[0]:
        lines.pop(0)
    while lines and not lines[-1]:
        lines.pop()
    return lines


def matches(expected: tuple[str, ...], printed: str) -> bool:
    """Whether `printed` is `expected`, each `...` line standing for any lines."""
    pattern = "".join(r"(?:.*\n)*?" if line == ELISION else re.escape(line) + r"\n"
                      for line in normal(expected))
    text = "".join(line + "\n" for line in normal(printed.splitlines()))
    return re.fullmatch(pattern, text) is not None


def workspace(tmp_path: Path) -> Path:
    """A folder with a copy of the sample data, where a page's commands run."""
    shutil.copytree(ROOT / "sample_data", tmp_path / "sample_data")
    return tmp_path


def _name(page: Path) -> str:
    return str(page.relative_to(ROOT))


@pytest.mark.parametrize("page", [
    pytest.param(page, id=_name(page),
                 marks=[] if page.name in QUICK_PAGES else [pytest.mark.slow])
    for page in PAGES])
def test_every_command_shown_runs_and_prints_what_the_page_shows(page, tmp_path):
    folder = workspace(tmp_path)
    for block in blocks(page):
        if block.kind in {"sh", "python"}:
            script = "\n".join(block.lines)
            if block.kind == "python":
                (folder / "example.py").write_text(script + "\n")
                script = f'"{sys.executable}" example.py'
            done = run(script, folder)
            assert done.returncode == 0, (f"{_name(page)}:{block.line}: the block ended with "
                                          f"status {done.returncode}:\n{done.stdout}")
        elif block.kind == "console":
            for command in shown(block):
                done = run(command.command, folder)
                assert matches(command.output, done.stdout), (
                    f"{_name(page)}:{block.line}: `{command.command}` printed\n{done.stdout}")


def test_every_block_of_commands_follows_the_convention():
    """A block with `$ ` prompts is a console block; commands are in console, sh or text
    blocks (text: said beside it why it is not run), so none escapes the run above."""
    for page in PAGES:
        for block in blocks(page):
            prompts = [line for line in block.lines if line.startswith("$ ")]
            assert not prompts or block.kind == "console", (_name(page), block.line)
            if block.kind in {"bash", "shell", "zsh", ""}:
                assert not any(line.lstrip().startswith("hamid ") for line in block.lines), (
                    f"{_name(page)}:{block.line}: commands go in a sh, console or text block")
        assert not _indented_commands(page), (
            f"{_name(page)}: commands in indented blocks, lines {_indented_commands(page)}: "
            "put them in a sh, console or text block")


def _indented_commands(page: Path) -> list[int]:
    """Lines outside fences indented as a code block that start a hamid command."""
    found, fenced = [], False
    for number, line in enumerate(page.read_text().splitlines(), start=1):
        if FENCE.match(line):
            fenced = not fenced
        elif not fenced and re.match(r"(    |\t)(\$ )?hamid ", line):
            found.append(number)
    return found


def test_the_readme_shows_a_first_fit_with_its_output():
    first = [command for block in blocks(ROOT / "README.md") if block.kind == "console"
             for command in shown(block)]
    assert first and first[0].command.startswith("hamid fit sample_data/")
    assert any("std. error" in line for line in first[0].output)
    assert ELISION not in first[0].output   # shown whole


def test_the_readme_is_short_and_starts_with_its_set_up():
    """At most 300 lines, the install and the test command within the first 60."""
    readme = (ROOT / "README.md").read_text().splitlines()
    assert len(readme) <= 300
    head = [line.strip() for line in readme[:60]]
    assert any(line.endswith("pip install . && hamid fit sample_data/peng_quadratic.csv")
               for line in head)
    assert any(line.endswith("pip install -q '.[test]' && python -m pytest") for line in head)


def test_the_comparison_can_fail():
    """An output that differs by one digit, or has a line more or less, does not match."""
    assert matches(("a 1.0", "...", "z"), "a 1.0\nb\nc\nz\n")
    assert matches(("a 1.0  ", "z"), "\na 1.0\nz  \n\n")
    assert not matches(("a 1.0", "z"), "a 1.1\nz\n")
    assert not matches(("a 1.0",), "a 1.0\nz\n")
    assert not matches(("a 1.0", "...", "z"), "a 1.0\nb\n")


def _rewritten(page: Path, folder: Path) -> str:
    """The page with each console block's outputs made again by running its commands, in
    order (a block that elides lines is run but kept as it is)."""
    lines = page.read_text().splitlines()
    replaced = []
    for block in blocks(page):
        if block.kind == "sh":
            run("\n".join(block.lines), folder)
        elif block.kind == "console":
            new = []
            for command in shown(block):
                new += ["$ " + command.command, *normal(run(command.command, folder).stdout
                                                        .splitlines())]
            if not any(ELISION in c.output for c in shown(block)):
                replaced.append((block, "\n".join(new).splitlines()))
    for block, new in reversed(replaced):
        indent = FENCE.match(lines[block.line - 1]).group(1)
        lines[block.line:block.line + len(block.lines)] = [(indent + x).rstrip() for x in new]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":   # rewrite the console outputs of the pages named
    import tempfile

    for name in sys.argv[1:]:
        target = Path(name).resolve()
        with tempfile.TemporaryDirectory() as scratch:
            target.write_text(_rewritten(target, workspace(Path(scratch))))
