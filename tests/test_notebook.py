"""The example notebook runs from top to bottom in a fresh kernel (nbclient), shows the
result as HTML and the figures as images, and its fitted motion stays near the truth;
examples/make_figures.py saves those figures."""

from __future__ import annotations

import importlib.util
import io
from pathlib import Path

import pytest

pytest.importorskip("nbclient")
pytest.importorskip("matplotlib")

from matplotlib.image import imread  # noqa: E402

SCRIPT = Path(__file__).resolve().parent.parent / "examples" / "make_figures.py"


@pytest.fixture(scope="module")
def script():
    spec = importlib.util.spec_from_file_location("make_figures", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def notebook(script):
    return script.run()


def _outputs(notebook, source_start: str) -> list:
    (cell,) = [c for c in notebook.cells if c.cell_type == "code"
               and c.source.startswith(source_start)]
    return cell.outputs


def test_notebook_runs_without_errors(notebook):
    errors = [o for c in notebook.cells if c.cell_type == "code" for o in c.outputs
              if o.output_type == "error"]
    assert errors == []


def test_notebook_shows_the_result_as_tables(notebook):
    (shown,) = _outputs(notebook, "result = hamid.fit(record)")
    assert shown["data"]["text/html"].startswith('<div class="hamid-fit">')
    assert "<h4>Parameters</h4>" in shown["data"]["text/html"]


def test_the_fitted_motion_stays_near_the_truth(notebook):
    (deviation,) = _outputs(notebook, "t = np.arange")
    text = deviation["data"]["text/plain"]
    values = dict(line.split() for line in text.splitlines() if line[:1] in "xv")
    assert set(values) == {"x", "v"} and max(map(float, values.values())) < 0.02


def test_make_figures_saves_every_tagged_figure(script, notebook, tmp_path):
    images = script.figures(notebook)
    assert sorted(images) == ["duffing-energy-phase", "duffing-parameters",
                              "duffing-residuals-motion"]
    for png in images.values():
        pixels = imread(io.BytesIO(png))[..., :3]
        assert pixels.shape[1] >= 1000 and pixels.std() > 0.1


def test_a_slow_kernel_loses_no_output(script, monkeypatch):
    """nbclient's default waits 4 s for a cell's outputs and then drops them silently; the
    notebook is run with minutes, and a wait that runs out is an error."""
    settings = {}

    class Client:
        def __init__(self, document, **kwargs):
            settings.update(kwargs)

        def execute(self):
            pass

    monkeypatch.setattr(script, "NotebookClient", Client)
    script.run()
    assert settings["timeout"] >= 600 and settings["iopub_timeout"] >= 600
    assert settings["raise_on_iopub_timeout"] is True
