"""The test run's own set-up (tests/conftest.py): child processes run this working tree, and
CI draws the same Hypothesis examples every time."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from helpers import hamid_command

ROOT = Path(__file__).resolve().parents[1]


def test_a_child_in_another_folder_imports_this_working_tree(tmp_path):
    done = subprocess.run([sys.executable, "-c", "import hamid; print(hamid.__file__)"],
                          capture_output=True, text=True, check=True, cwd=tmp_path,
                          timeout=600)
    assert Path(done.stdout.strip()) == ROOT / "hamid" / "__init__.py"


def test_the_command_line_is_not_a_hamid_script_found_on_path(tmp_path):
    script = tmp_path / "bin" / "hamid"
    script.parent.mkdir()
    script.write_text("#!/bin/sh\necho another copy; exit 42\n")
    script.chmod(0o755)
    env = {**os.environ, "PATH": os.pathsep.join([str(script.parent), os.environ["PATH"]])}
    done = subprocess.run([*hamid_command(), "--version"], capture_output=True, text=True,
                          cwd=tmp_path, env=env, timeout=600)
    assert done.returncode == 0, done.stderr
    assert "another copy" not in done.stdout


def test_ci_loads_a_derandomized_hypothesis_profile(tmp_path):
    probe = ("import conftest\nfrom hypothesis import settings\n"
             "print(settings.default.derandomize, settings.default.deadline)")
    env = {**os.environ, "CI": "true",
           "PYTHONPATH": os.pathsep.join([str(ROOT / "tests"), os.environ["PYTHONPATH"]])}
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                          check=True, cwd=tmp_path, env=env, timeout=600)
    assert done.stdout.split() == ["True", "None"]


def test_the_readme_test_command_is_what_ci_runs():
    """Word for word, and in a folder of its own: two runs at once share no environment."""
    readme = (ROOT / "README.md").read_text().splitlines()
    start = next(i for i, line in enumerate(readme)
                 if line.startswith("Install and run the tests"))
    command = next(line.strip() for line in readme[start:] if line.startswith("    "))
    assert command in (ROOT / ".ci" / "run").read_text().splitlines()
    assert "mktemp -d" in command and "/tmp/" not in command
