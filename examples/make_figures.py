"""Run the example notebook and save its figures as PNG files (docs/img/ by default).

    python examples/make_figures.py [FOLDER]

Each figure cell of examples/identify_a_duffing_oscillator.ipynb carries a tag
``figure:NAME``; its image is written to FOLDER/NAME.png, so that the pictures in the
README are the notebook's own. Needs ``pip install 'hamid[plot,test]'`` (nbclient and a
kernel).
"""

from __future__ import annotations

import base64
import sys
from pathlib import Path

import nbformat
from nbclient import NotebookClient

HERE = Path(__file__).resolve().parent
NOTEBOOK = HERE / "identify_a_duffing_oscillator.ipynb"


def run(notebook: Path = NOTEBOOK) -> nbformat.NotebookNode:
    """The notebook executed in a fresh kernel, in its own folder."""
    document = nbformat.read(notebook, as_version=4)
    # nbclient waits 4 s for a cell's outputs after it ends, then drops them silently: on a
    # busy machine a figure would be lost. Minutes, and an error rather than a lost output.
    NotebookClient(document, timeout=600, iopub_timeout=600, raise_on_iopub_timeout=True,
                   kernel_name="python3",
                   resources={"metadata": {"path": str(notebook.parent)}}).execute()
    return document


def figures(document: nbformat.NotebookNode) -> dict[str, bytes]:
    """The PNG image of every cell tagged ``figure:NAME``, by name."""
    found = {}
    for cell in document.cells:
        for tag in cell.get("metadata", {}).get("tags", []):
            if tag.startswith("figure:"):
                (image,) = [o["data"]["image/png"] for o in cell.outputs
                            if "image/png" in o.get("data", {})]
                found[tag.removeprefix("figure:")] = base64.b64decode(image)
    return found


def main(folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name, png in figures(run()).items():
        (folder / f"{name}.png").write_bytes(png)
        print(folder / f"{name}.png")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else HERE.parent / "docs" / "img")
