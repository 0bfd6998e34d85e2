"""The package's layering: a module imports only modules of its own layer or below (imports
inside functions included), and no two modules import each other, directly or around a cycle."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).parent.parent / "slcvjax"

# lowest first: what a layer may build on is every layer above it in this list
LAYERS = [
    ("support", {"_safe", "_cache", "_persist"}),
    ("geometry", {"_pose", "_newton", "_camera", "_lasers", "_revolution", "_conic", "_mirror", "_rig"}),
    ("observations", {"_io", "_problem", "_simulate", "_published"}),
    ("calibration", {"_lm", "_staged", "_central", "_rigid", "_calibrate", "_implicit", "_chessboard"}),
    ("measurement", {"_measure"}),
    ("images", {"_detect", "_pipe", "_render", "_centroids"}),
    ("plots", {"_plots"}),
    ("experiments", {"_sweep", "_design", "_laser_design", "_omni"}),
    ("interfaces", {"cli", "__init__"}),
]


def _imports() -> dict[str, set[str]]:
    out = {}
    for path in PACKAGE.glob("*.py"):
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 1 and node.module:
                deps.add(node.module.split(".")[0])
            elif isinstance(node, ast.ImportFrom) and node.level == 1:  # from . import x
                deps.update(a.name for a in node.names)
        out[path.stem] = deps
    return out


def test_every_module_has_a_layer():
    placed = set().union(*(mods for _, mods in LAYERS))
    assert set(_imports()) == placed


def test_no_module_imports_a_higher_layer():
    level = {m: i for i, (_, mods) in enumerate(LAYERS) for m in mods}
    bad = [
        f"{m} ({LAYERS[level[m]][0]}) imports {d} ({LAYERS[level[d]][0]})"
        for m, deps in _imports().items()
        for d in deps
        if level[d] > level[m]
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
