"""The package's layering: the subpackages are the pipeline's layers, and a module imports only
modules of its own layer or below (imports inside functions included); no two modules import
each other, directly or around a cycle."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).parent.parent / "slcvjax"

# lowest first: a layer may build on every layer before it in this list
LAYERS = [
    "support",
    "geometry",
    "observations",
    "calibration",
    "measurement",
    "images",
    "plots",
    "experiments",
    "cli",
    "__init__",
]


def _name(path: Path) -> str:
    """The module's dotted name under ``slcvjax`` (a package is named by its folder)."""
    parts = path.relative_to(PACKAGE).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" and len(parts) > 1 else parts)


def _is_package(path: Path) -> bool:
    return path.name == "__init__.py"


def _imports() -> dict[str, set[str]]:
    """Each module's imports of other ``slcvjax`` modules, as dotted names under ``slcvjax``."""
    modules = {_name(p): p for p in PACKAGE.rglob("*.py")}
    out = {}
    for name, path in modules.items():
        here = [] if name == "__init__" else name.split(".")
        base = here if _is_package(path) else here[:-1]
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level >= 1:
                anchor = base[: len(base) - (node.level - 1)] if node.level > 1 else base
                mod = anchor + (node.module.split(".") if node.module else [])
                for alias in node.names:  # `from .pkg import module` imports the module
                    full = ".".join(mod + [alias.name])
                    deps.add(full if full in modules else ".".join(mod))
            elif isinstance(node, ast.Import | ast.ImportFrom):
                names = [node.module] if isinstance(node, ast.ImportFrom) else [a.name for a in node.names]
                for n in names:
                    if n and n.split(".")[0] == "slcvjax":
                        deps.add(".".join(n.split(".")[1:]) or "__init__")
        out[name] = {d or "__init__" for d in deps} - {name}
    return out


def _layer(module: str) -> str:
    return module.split(".")[0]


def test_every_module_has_a_layer():
    names = set(_imports())
    assert {_layer(m) for m in names} <= set(LAYERS), sorted(m for m in names if _layer(m) not in LAYERS)
    # the layers are folders: no module of the package lies loose beside them
    loose = [p.name for p in PACKAGE.glob("*.py") if p.stem not in LAYERS]
    assert not loose, loose


def test_the_imports_are_resolved():
    """Every import this test reads names a module of the package (the checks below see them all)."""
    modules = set(_imports())
    unknown = {f"{m} imports {d}" for m, deps in _imports().items() for d in deps if d not in modules}
    assert not unknown, "\n".join(sorted(unknown))


def test_no_module_imports_a_higher_layer():
    level = {name: i for i, name in enumerate(LAYERS)}
    bad = [
        f"{m} ({_layer(m)}) imports {d} ({_layer(d)})"
        for m, deps in _imports().items()
        for d in deps
        if level[_layer(d)] > level[_layer(m)]
    ]
    assert not bad, "\n".join(bad)


def test_no_import_cycles():
    graph = _imports()
    state: dict[str, int] = {}  # 1 on the path, 2 done
    cycles = []

    def visit(m, path):
        state[m] = 1
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                cycles.append(" -> ".join(path[path.index(d) :] + [d]))
            elif d not in state:
                visit(d, path + [d])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert not cycles, "\n".join(cycles)


# the calibration package's modules, lowest first: a module imports only those before it
CALIBRATION = [
    "options",
    "base",
    "laser_fit",
    "sheet_fit",
    "staged",
    "central",
    "params",
    "residuals",
    "schur",
    "losses",
    "linearise",
    "lm",
    "evaluate",
    "chessboard",
    "covariance",
    "rigid",
    "result",
    "executors",
    "trial",
    "passes",
    "board_starts",
    "repairs",
    "schedule",
    "rigid_pass",
    "bound",
    "implicit",
    "stored",
    "consistency",
    "report",
    "model_selection",
    "calibrate",
]


def test_calibration_modules_are_layered():
    graph = _imports()
    mods = {m.split(".", 1)[1] for m in graph if m.startswith("calibration.")}
    assert mods == set(CALIBRATION), sorted(mods ^ set(CALIBRATION))
    rank = {m: i for i, m in enumerate(CALIBRATION)}
    bad = [
        f"calibration.{m} imports {d}"
        for m in CALIBRATION
        for d in graph[f"calibration.{m}"]
        if d.startswith("calibration.") and rank[d.split(".", 1)[1]] >= rank[m]
    ]
    assert not bad, "\n".join(bad)


def _private_uses(path: Path) -> list[str]:
    """The private names (a leading underscore) ``path`` takes from another ``slcvjax`` module:
    imported by name, or read as an attribute of an imported ``slcvjax`` module."""
    tree = ast.parse(path.read_text())
    in_package = PACKAGE in path.parents
    out, modules = [], set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            ours = (node.module or "").split(".")[0] == "slcvjax" or (in_package and node.level >= 1)
            if not ours:
                continue
            for a in node.names:
                if a.name.startswith("_") and not a.name.startswith("__"):
                    out.append(f"{path.name}:{node.lineno} imports {a.name}")
                modules.add(a.asname or a.name)  # perhaps a module (`from slcvjax.x import y as z`)
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "slcvjax":
                    modules.add(a.asname or a.name.split(".")[0])
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Attribute)
            and node.attr.startswith("_")
            and not node.attr.startswith("__")
            and isinstance(node.value, ast.Name)
            and node.value.id in modules
        ):
            out.append(f"{path.name}:{node.lineno} reads {node.value.id}.{node.attr}")
    return out


def test_no_module_takes_another_modules_private_names():
    """Neither the package nor the tests reach into a module's private names: what another
    module uses is public (the package's layering test then sees every dependency)."""
    files = list(PACKAGE.rglob("*.py")) + list(Path(__file__).parent.glob("*.py"))
    bad = [u for p in files for u in _private_uses(p)]
    assert not bad, "\n".join(bad)
