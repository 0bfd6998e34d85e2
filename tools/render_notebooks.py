"""Execute the notebooks for the documentation: ``docs/notebooks/*.ipynb`` with their outputs.

``notebooks/`` holds the notebooks without outputs (what a user opens and what the tests run);
the documentation shows these copies, executed in a fresh kernel each at the notebooks' small
size (``SLCV_NOTEBOOK_SMALL=1``), each in its own temporary folder.  Run it after changing a
notebook (``tests/test_notebooks.py`` checks that the copies hold the same code, with outputs and
no error)::

    python tools/render_notebooks.py            # every notebook
    python tools/render_notebooks.py 03         # those whose name starts with 03
"""

import os
import sys
import tempfile
import time
from pathlib import Path

import nbformat
from nbclient import NotebookClient

ROOT = Path(__file__).resolve().parent.parent
SOURCE, TARGET = ROOT / "notebooks", ROOT / "docs" / "notebooks"


def render(path: Path) -> Path:
    """Execute ``path`` (a notebook of ``notebooks/``) and write it, outputs included, to ``docs/notebooks/``."""
    nb = nbformat.read(path, as_version=4)
    os.environ["SLCV_NOTEBOOK_SMALL"] = "1"
    os.environ.pop("MPLBACKEND", None)  # the kernel's inline backend: figures become outputs
    with tempfile.TemporaryDirectory() as tmp:
        NotebookClient(nb, timeout=1200, kernel_name="python3", resources={"metadata": {"path": tmp}}).execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"]
    if errors:
        raise RuntimeError(f"{path.name}: {errors[0].get('ename')}: {errors[0].get('evalue')}")
    nb.metadata.pop("widgets", None)
    TARGET.mkdir(parents=True, exist_ok=True)
    out = TARGET / path.name
    nbformat.write(nb, out)
    return out


def main(prefixes: list[str]) -> None:
    paths = sorted(p for p in SOURCE.glob("*.ipynb") if not prefixes or any(p.name.startswith(x) for x in prefixes))
    for p in paths:
        t0 = time.perf_counter()
        out = render(p)
        print(f"{out.relative_to(ROOT)}: {time.perf_counter() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
