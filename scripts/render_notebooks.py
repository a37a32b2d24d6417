"""Execute the notebooks (jupytext sources in ``notebooks/``) and write them with their
outputs to ``docs/notebooks/*.ipynb``, which the documentation site renders as they are.

    python scripts/render_notebooks.py                 # all of them, full size
    python scripts/render_notebooks.py 04_real_data    # one
    DIFFCAM_NOTEBOOK_SMALL=1 python scripts/render_notebooks.py   # reduced size

Each notebook runs in a fresh kernel in a temporary folder (the figures it also saves
go there), with progress reports off (``DIFFCAM_PROGRESS=0``): the page shows the
notebook's own output only. ``tests/test_docs.py`` checks that every rendered notebook
holds the code of its source and shows its figures, and no stderr or stray value.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ROOT / "notebooks"
RENDERED = ROOT / "docs" / "notebooks"


def render(source: Path, timeout: float = 3600) -> Path:
    """Execute ``source`` and write ``docs/notebooks/<stem>.ipynb``; return its path."""
    import jupytext
    import nbformat
    from nbclient import NotebookClient

    notebook = jupytext.read(source)
    with tempfile.TemporaryDirectory() as work:
        os.environ["DIFFCAM_FIGURES"] = str(Path(work) / "figures")
        os.environ["DIFFCAM_PROGRESS"] = "0"
        NotebookClient(notebook, timeout=timeout, kernel_name="python3",
                       resources={"metadata": {"path": work}}).execute()
    notebook.metadata.pop("jupytext", None)
    RENDERED.mkdir(parents=True, exist_ok=True)
    out = RENDERED / f"{source.stem}.ipynb"
    tmp = out.with_suffix(".ipynb.tmp")
    nbformat.write(notebook, tmp)
    tmp.replace(out)
    return out


def main(names: list[str]) -> None:
    sources = sorted(SOURCES.glob("*.py"))
    if names:
        sources = [s for s in sources if s.stem in names]
    for source in sources:
        t = time.perf_counter()
        out = render(source)
        print(f"{out.relative_to(ROOT)}: {time.perf_counter() - t:.0f} s", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
