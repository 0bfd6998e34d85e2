"""MkDocs hook: the API reference page (``api.md``), generated from ``slcvjax.__all__`` at every build.

The public names are read from ``slcvjax/__init__.py`` without importing it (no JAX): its
``__all__``, the module each name is imported from, and the lazily imported names (``_LAZY``).
A name is documented through the package (``slcvjax.NAME``), where mkdocstrings resolves the
re-export; a lazy name through the module that defines it, except under ``slcvjax.calibration``
(being reorganised), which are listed by name only.
"""

import ast
from pathlib import Path

from mkdocs.structure.files import File

INIT = Path(__file__).resolve().parents[2] / "slcvjax" / "__init__.py"

SECTIONS = {
    "geometry": "Geometry: camera, mirrors, lasers, the rig",
    "observations": "Observations, files and simulation",
    "calibration": "Calibration",
    "measurement": "Measurement",
    "images": "Images: render and detect",
    "plots": "Plots",
    "experiments": "Experiments: sweeps, design, catadioptric cameras",
    "support": "Caches",
}

INTRO = """# API reference

Every public name of the package (`import slcvjax as sj`; `sj.__all__` lists them), grouped by the layer
that defines it. This page is generated from `slcvjax/__init__.py` and the docstrings when the site is
built. Shapes, frames and units are stated in each docstring; lengths are millimetres, angles radians.
"""


def public_names() -> dict[str, tuple[str, bool]]:
    """``name -> (defining module under slcvjax, lazy?)`` for every name in ``__all__``."""
    tree = ast.parse(INIT.read_text())
    where: dict[str, tuple[str, bool]] = {}
    exported: list[str] = []
    for node in tree.body:
        if isinstance(node, ast.ImportFrom) and node.level == 1 and node.module:
            for alias in node.names:
                where[alias.asname or alias.name] = (node.module, False)
        elif isinstance(node, ast.Assign | ast.AnnAssign):
            target = node.targets[0] if isinstance(node, ast.Assign) else node.target
            if isinstance(target, ast.Name) and target.id == "_LAZY":
                for k, v in zip(node.value.keys, node.value.values, strict=True):
                    where[k.value] = (v.value, True)
            elif isinstance(target, ast.Name) and target.id == "__all__":
                exported = [e.value for e in node.value.elts]
            elif isinstance(target, ast.Name):
                where.setdefault(target.id, ("", False))
    return {n: where.get(n, ("", False)) for n in exported}


def render() -> str:
    groups: dict[str, list[tuple[str, str, bool]]] = {}
    for name, (module, lazy) in public_names().items():
        groups.setdefault(module.split(".")[0] or "support", []).append((name, module, lazy))
    parts = [INTRO]
    unlisted = []
    for layer, title in SECTIONS.items():
        names = sorted(groups.get(layer, []), key=lambda x: (not x[0][0].isupper(), x[0].lower()))
        shown = []
        for name, module, lazy in names:
            if not lazy:
                shown.append(f"::: slcvjax.{name}\n")
            elif layer != "calibration":
                shown.append(f"::: slcvjax.{module}.{name}\n")
            else:
                unlisted.append(name)
        if shown:
            parts.append(f"## {title}\n")
            parts.extend(shown)
    if unlisted:
        parts.append("## Also public\n")
        parts.append(
            "Imported on first use, and documented in their docstrings (`help(sj.NAME)`): "
            + ", ".join(f"`sj.{n}`" for n in sorted(unlisted))
            + ".\n"
        )
    return "\n".join(parts)


def on_files(files, config):
    files.append(File.generated(config, "api.md", content=render()))
    return files
