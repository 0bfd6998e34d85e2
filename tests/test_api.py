"""The public API: every job is a name of the package, the notebooks and the documentation's code use
only those names, and ``import slcvjax`` loads the image, experiment and plot layers only when
one of their names is used."""

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

import slcvjax

ROOT = Path(__file__).parent.parent
PRIVATE_IMPORT = re.compile(r"^\s*(from slcvjax\.[\w.]+ import|import slcvjax\.)", re.M)


def test_every_public_name_resolves():
    for name in slcvjax.__all__:
        assert getattr(slcvjax, name) is not None, name
    assert set(slcvjax.__all__) <= set(dir(slcvjax))


def test_a_lazy_name_is_the_defining_modules():
    from slcvjax.experiments.sweep import run_sweep
    from slcvjax.images.detect import detect_folder

    assert slcvjax.run_sweep is run_sweep and slcvjax.detect_folder is detect_folder


def test_an_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'calibrat'"):
        slcvjax.calibrat  # noqa: B018


def test_import_loads_only_the_calibration():
    code = (
        "import sys, slcvjax\n"
        "late = [m for m in sys.modules if m.startswith(('slcvjax.images', 'slcvjax.experiments', "
        "'slcvjax.plots', 'slcvjax.cli', 'matplotlib', 'scipy'))]\n"
        "print(late)\n"
        "slcvjax.plot_rig\n"
        "print('slcvjax.plots' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split("\n")
    assert out[0] == "[]" and out[1] == "True"


def _notebook_code(path: Path) -> str:
    cells = json.loads(path.read_text())["cells"]
    return "\n".join("".join(c["source"]) for c in cells if c["cell_type"] == "code")


@pytest.mark.parametrize("path", sorted((ROOT / "notebooks").glob("*.ipynb")), ids=lambda p: p.name)
def test_notebooks_use_only_the_public_api(path):
    code = _notebook_code(path)
    assert "slcvjax" in code
    assert not PRIVATE_IMPORT.findall(code)
    used = set(re.findall(r"\bsj\.(\w+)", code)) | {
        n.strip() for m in re.findall(r"from slcvjax import ([\w, ]+)", code) for n in m.split(",")
    }
    assert used and used <= set(slcvjax.__all__), sorted(used - set(slcvjax.__all__))


def test_the_documentation_code_uses_only_the_public_api():
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    blocks = [b for p in pages for b in re.findall(r"```python\n(.*?)```", p.read_text(), re.S)]
    assert blocks
    code = "\n".join(blocks)
    assert not PRIVATE_IMPORT.findall(code)
    used = set(re.findall(r"\bsj\.(\w+)", code)) | {
        n.strip() for m in re.findall(r"from slcvjax import ([\w, ]+)", code) for n in m.split(",")
    }
    assert used <= set(slcvjax.__all__), sorted(used - set(slcvjax.__all__))
