"""The documentation site (docs/, Sphinx with myst-parser; the `docs` extra) builds with
warnings as errors: a broken link between pages, a missing image, a docstring autodoc
cannot read fail here, as in CI. It is built into a temporary folder, never into the
repository."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _files(folder: Path) -> set[Path]:
    return {path for path in folder.rglob("*") if "__pycache__" not in path.parts}


def test_the_site_builds_with_warnings_as_errors(tmp_path):
    before = _files(ROOT / "docs")
    site = tmp_path / "site"
    done = subprocess.run(
        [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html",
         "-d", str(tmp_path / "doctrees"), str(ROOT / "docs"), str(site)],
        capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stderr == "", done.stderr
    assert _files(ROOT / "docs") == before   # nothing written into the repository
    api = (site / "api.html").read_text()
    # the reference is generated from the docstrings: their first lines appear in it
    import hamid.api
    first_line = hamid.api.fit.__doc__.strip().splitlines()[0]
    assert "hamid.api.fit" in api and first_line in api
    for page in ("index.html", "readme.html", "guide/tutorial.html", "method.html",
                 "output.html", "architecture.html", "scaling.html"):
        assert (site / page).is_file(), page
    assert (site / "_images" / "duffing-energy-phase.png").is_file()


def test_every_page_is_in_the_site():
    """A Markdown page under docs/ left out of every table of contents would be a warning,
    and so an error above; this names the pages the index must reach."""
    index = (ROOT / "docs" / "index.md").read_text()
    pages = {str(path.relative_to(ROOT / "docs").with_suffix(""))
             for path in (ROOT / "docs").rglob("*.md")}
    assert pages - {"index"} <= {line.strip() for line in index.splitlines()}
