"""Fuzzing the public file readers (issue 61, item 4).

Valid files of every format the project reads (``slcv-observations/1``, ``slcv-calibration/1``,
``slcv-setup/1``, and the fields of them read after the reader: a calibration's residual sigma
and covariance for ``measure``, an observation file's ``detection`` sizes and ``rigid_boards``)
are mutated: values, types, missing and extra fields, huge and tiny numbers, NaN as text and
as JSON's ``NaN``, wrong nesting, empty lists, broken bytes.  Every reader either reads the file
into values that hold the format's invariants (finite numbers, shapes, indices in range), or
raises ``FormatError`` with one line ``<file>: <field[index]>: <why>``; never another exception,
and it writes nothing.
"""

import copy
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from slcvjax.images.centroids import detection_sizes
from slcvjax.images.detect import read_setup, setup_to_json
from slcvjax.images.pipe import measurement_inputs
from slcvjax.images.render import scene_setup
from slcvjax.observations.formats import (
    FormatError,
    calibration_to_json,
    observations_to_json,
    read_calibration,
    read_observations,
)
from slcvjax.observations.simulate import make_scene, simulate

# the mutated files are inputs outside the formats on purpose: the suite's schema check leaves them
pytestmark = pytest.mark.hand_written_inputs

FAST = 200  # examples per format in the fast tier
SLOW = 3000  # in the slow one

# --------------------------------------------------------------------------- valid files


def _observations_docs(obs) -> list[dict]:
    doc = observations_to_json(obs)
    n = len(obs.boards["wall1"])
    doc["rigid_boards"] = ["wall0", "wall1", "wall2", "wall3"]
    doc["detection"] = {
        "dot_radius_mm": {"wall0": 2.0, "wall1": 2.0, "wall2": None},
        "spot_sigma_mm": 0.4,
        "ambiguous_boards": [
            {
                "view": 1,
                "board": "wall1",
                "candidates": [
                    {"pixels": [[100.0 + i, 200.0] for i in range(4)], "indices": [0, 1, 2, 3]},
                    {"pixels": [[100.0 + i, 201.0] for i in range(4)], "indices": [n - 4, n - 3, n - 2, n - 1]},
                ],
            }
        ],
    }
    conic = copy.deepcopy(doc)
    conic["mirror_shape"] = {"kind": "hyperboloid", "vertex_radius": 20.0}  # a conic, partly given
    conic["camera_projection"] = "auto"
    asphere = copy.deepcopy(doc)  # every dimension given, the coefficients a list
    asphere["mirror_shape"] = {
        "kind": "asphere",
        "vertex_radius": 20.0,
        "conic_constant": -1.5,
        "coefficients": [1e-6, -1e-9],
        "radius": 15.0,
    }
    return [doc, conic, asphere]


def _calibration_docs(truth) -> list[dict]:
    doc = calibration_to_json(truth)
    g = 9 + 6 + 4 * len(doc["lasers"])
    doc["residuals"] = {"rms_px": 0.42, "sigma_px": 0.3, "by_kind_sigma_px": {"spot": 0.25, "dot": 0.3}}
    doc["uncertainty"] = {"covariance": {"matrix": (np.eye(g) * 1e-4).tolist()}}
    undetermined = copy.deepcopy(doc)
    undetermined["lasers"][1] = {"point": None, "direction": None, "status": "undetermined"}
    camera_only = {"format": doc["format"], "camera": copy.deepcopy(doc["camera"])}
    camera_only["camera"].update(projection="telecentric", unit_mm=0.05)
    conic = copy.deepcopy(doc)  # a hyperboloid mirror in place of the cone
    conic["mirror"] = {
        "kind": "hyperboloid",
        "vertex_radius": 20.0,
        "conic_constant": -2.0,
        "radius": 15.0,
        "apex": doc["mirror"]["apex"],
        "axis": doc["mirror"]["axis"],
    }
    return [doc, undetermined, camera_only, conic]


@pytest.fixture(scope="module")
def valid(tmp_path_factory):
    """{format: [valid documents]}: a small simulated scene's files, with the optional fields."""
    scene = make_scene("paper", n_lasers=3, n_views=2)
    obs, truth = simulate(scene, noise=0.3, seed=3)
    setup = scene_setup(scene, [f"view{i:02d}.png" for i in range(2)], ["chess00.png"])
    setup.spot_sigma_mm = 0.4
    setup.rigid_boards = ["wall0", "wall1"]
    setup.laser_azimuth_deg = [10.0, 130.0, 250.0]
    for b in setup.boards.values():
        if b.azimuth_deg is not None:
            b.dot_radius_mm = 2.0
    docs = {
        "observations": _observations_docs(obs),
        "calibration": _calibration_docs(truth),
        "setup": [setup_to_json(setup)],
    }
    # each reads as it is (else the fuzzing starts from a broken file)
    folder = tmp_path_factory.mktemp("valid")
    for kind, ds in docs.items():
        for k, d in enumerate(ds):
            path = folder / f"{kind}{k}.json"
            path.write_text(json.dumps(d))
            READERS[kind](path)
    return docs


# --------------------------------------------------------------------------- readers and their invariants


def _finite(a, shape_tail=None) -> None:
    a = np.asarray(a)
    assert a.dtype.kind == "f" and np.all(np.isfinite(a)), a
    if shape_tail is not None:
        assert a.shape[a.ndim - len(shape_tail) :] == shape_tail, a.shape


def _positive_number(x) -> None:
    assert isinstance(x, float) and math.isfinite(x) and x > 0, x


def read_obs(path):
    obs = read_observations(path)
    w, h = obs.image_size
    assert isinstance(w, int) and isinstance(h, int) and w > 0 and h > 0
    assert isinstance(obs.n_lasers, int) and obs.n_lasers >= 0
    assert math.isfinite(obs.mirror_radius) and math.isfinite(obs.mirror_height)
    for pts in obs.boards.values():
        _finite(pts, (3,))
        assert len(pts) > 0 and np.all(pts[:, 2] == 0.0)
    for v in obs.calibration_views:
        assert v.board in obs.boards and isinstance(v.name, str)
        _finite(v.pixels, (len(obs.boards[v.board]), 2))
    for v in obs.views:
        assert isinstance(v.name, str)
        for b, (px, seen) in v.boards.items():
            assert b in obs.boards and seen.dtype == bool
            _finite(px, (len(obs.boards[b]), 2))
        for s in v.spots:
            assert 0 <= s.laser < obs.n_lasers and (s.board is None or s.board in obs.boards)
            _finite(s.pixel, (2,))
        _finite(np.asarray(v.rim, float).reshape(-1, 2))
    # the fields read after the reader: the detection's sizes, the rigid group
    radii, sigma = detection_sizes(obs)
    assert set(radii) <= set(obs.boards)
    for r in radii.values():
        _positive_number(r)
    if sigma is not None:
        _positive_number(sigma)
    rigid = obs.extra.get("rigid_boards") or []
    assert isinstance(rigid, list) and all(isinstance(b, str) and b in obs.boards for b in rigid)
    amb = (obs.extra.get("detection") or {}).get("ambiguous_boards") or []
    for e in amb:
        assert 0 <= e["view"] < len(obs.views) and e["board"] in obs.boards
        assert len(e["candidates"]) >= 2
        for c in e["candidates"]:
            idx = c["indices"]
            assert all(type(k) is int and 0 <= k < len(obs.boards[e["board"]]) for k in idx)
            assert len(c["pixels"]) == len(idx) == len(set(idx))
            _finite(np.asarray(c["pixels"], float).reshape(-1, 2))
    return obs


def read_cal(path):
    cal = read_calibration(path)
    cam = cal.rig.camera
    assert cam.width > 0 and cam.height > 0
    _finite(cam.K, (3, 3))
    _finite(cam.dist, (5,))
    assert float(cam.fx) > 0 and float(cam.fy) > 0
    if cal.rig.mirror is not None:
        _finite(cal.rig.mirror.apex, (3,))
        _finite(cal.rig.mirror.axis, (3,))
        assert abs(np.linalg.norm(np.asarray(cal.rig.mirror.axis)) - 1.0) < 1e-9
    _finite(np.asarray(cal.rig.lasers.points).reshape(-1, 3))
    d = np.asarray(cal.rig.lasers.directions).reshape(-1, 3)
    _finite(d)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    for view in cal.board_poses:
        for p in view.values():
            _finite(p.R, (3, 3))
            _finite(p.t, (3,))
    # what ``measure`` reads of it after the reader: the pixel sigma and the covariance
    if cal.rig.mirror is not None and cal.rig.lasers.n > 0:
        sigma, cov = measurement_inputs(path, cal)
        assert sigma is None or (isinstance(sigma, float) and math.isfinite(sigma) and sigma >= 0), sigma
        if cov is not None:
            _finite(cov, (cal.rig.tangent_dim, cal.rig.tangent_dim))
    return cal


def read_set(path):
    setup = read_setup(path)
    w, h = setup.image_size
    assert w > 0 and h > 0 and setup.n_lasers >= 0
    for b in setup.boards.values():
        _finite(b.points, (3,))
        assert b.cols * b.rows == len(b.points) and b.cols >= 1 and b.rows >= 1
        assert b.x_dir in (1, -1) and b.y_dir in (1, -1)
        if b.azimuth_deg is not None:
            assert math.isfinite(b.azimuth_deg)
        if b.dot_radius_mm is not None:
            _positive_number(b.dot_radius_mm)
    assert all(isinstance(v, str) for v in setup.views)
    assert all(isinstance(im, str) and b in setup.boards for im, b in setup.chessboard_views)
    if setup.laser_azimuth_deg is not None:
        assert len(setup.laser_azimuth_deg) == setup.n_lasers
        _finite(np.asarray(setup.laser_azimuth_deg, float))
    if setup.spot_sigma_mm is not None:
        _positive_number(setup.spot_sigma_mm)
    assert all(b in setup.boards for b in setup.rigid_boards)
    return setup


READERS = {"observations": read_obs, "calibration": read_cal, "setup": read_set}

# --------------------------------------------------------------------------- mutations

ODD = [
    None, True, False, 0, 1, -1, 2, 3, 0.5, -0.5, 1e-300, 5e-324, -0.0, 1e308, -1e308, 10**400, -(10**400),
    2**63, float("nan"), float("inf"), float("-inf"), "NaN", "nan", "Infinity", "1.5", "", "x", "wall0", "cone",
    "slcv-calibration/1", [], {}, [0], [None], [1.0, 2.0], [1.0, 2.0, 3.0], [[1.0, 2.0]], [[None]], {"a": 1},
    {"kind": "cone"}, [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
]  # fmt: skip
values = st.one_of(
    st.sampled_from(ODD).map(copy.deepcopy),  # a later mutation must not change the list's own
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-(10**30), 10**30),
    st.text(max_size=4),
)


def _nodes(doc, path=()):
    """Every (path, node) of a document, containers first."""
    yield path, doc
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _nodes(v, path + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from _nodes(v, path + (i,))


@st.composite
def _path(draw, doc):
    """A node's path: a walk from the top (one in 20 the document itself) that goes down a random
    child three times in four."""
    path, node = [], doc
    while isinstance(node, (dict, list)) and node and draw(st.integers(0, 19 if not path else 3)) > 0:
        key = draw(st.sampled_from(list(node))) if isinstance(node, dict) else draw(st.integers(0, len(node) - 1))
        path.append(key)
        node = node[key]
    return path


def _set(doc, path, value):
    if not path:
        return value
    node = doc
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    return doc


def _get(doc, path):
    for k in path:
        doc = doc[k]
    return doc


@st.composite
def mutated_doc(draw, docs):
    doc = copy.deepcopy(draw(st.sampled_from(docs)))
    for _ in range(draw(st.integers(1, 3))):
        path = draw(_path(doc))
        node = _get(doc, path)
        op = draw(st.sampled_from(["value", "value", "delete", "extra", "empty", "wrap", "unwrap", "scale", "dup"]))
        if op == "value":
            doc = _set(doc, path, draw(values))
        elif op == "delete" and path:
            parent = _get(doc, path[:-1])
            del parent[path[-1]]
        elif op == "extra" and isinstance(node, dict):
            node[draw(st.sampled_from(["extra", "format", "kind", "points", "board", "laser", "x"]))] = draw(values)
        elif op == "empty":
            doc = _set(doc, path, [] if not isinstance(node, dict) else {})
        elif op == "wrap":
            doc = _set(doc, path, [node])
        elif op == "unwrap" and isinstance(node, (list, dict)) and node:
            doc = _set(doc, path, node[0] if isinstance(node, list) else next(iter(node.values())))
        elif op == "scale" and isinstance(node, (int, float)) and not isinstance(node, bool):
            doc = _set(doc, path, node * draw(st.sampled_from([1e300, 1e-300, -1, 1e17, 0])))
        elif op == "dup" and isinstance(node, list) and node:
            node.append(copy.deepcopy(node[draw(st.integers(0, len(node) - 1))]))
    return doc


@st.composite
def mutated_text(draw, docs):
    """The file's text: a mutated document, sometimes then broken as bytes."""
    text = json.dumps(draw(mutated_doc(docs)))  # Python writes NaN and Infinity as JSON's extensions
    data = text.encode()
    how = draw(st.sampled_from(["as is"] * 16 + ["truncate", "byte", "bom", "latin"]))
    if how == "truncate":
        data = data[: draw(st.integers(0, len(data)))]
    elif how == "byte" and data:
        i = draw(st.integers(0, len(data) - 1))
        data = data[:i] + bytes([draw(st.integers(0, 255))]) + data[i + 1 :]
    elif how == "bom":
        data = b"\xef\xbb\xbf" + data
    elif how == "latin":
        data = data.replace(b'"', b'"\xe9', 1)
    return data


MESSAGE = re.compile(r"^(?P<file>[^\n]+?\.json): (?P<field>[^:\n]+): (?P<why>[^\n]+)$")


def check_reader(kind: str, data: bytes, folder: Path) -> None:
    path = folder / f"fuzz_{kind}.json"
    path.write_bytes(data)
    before = sorted(p.name for p in folder.iterdir())
    try:
        READERS[kind](path)
    except FormatError as e:
        m = MESSAGE.match(str(e))
        assert m is not None, f"not one line '<file>: <field>: <why>': {e}"
        assert m["file"] == str(path), str(e)
        field = m["field"]
        assert field in ("(file)", "(top level)") or re.match(r"^[A-Za-z_]", field), str(e)
    assert sorted(p.name for p in folder.iterdir()) == before  # nothing written


def _fuzz(kind, n):
    @settings(max_examples=n, suppress_health_check=list(HealthCheck), deadline=None)
    @given(data=st.data())
    def run(valid, tmp_path_factory, data):
        folder = tmp_path_factory.mktemp("fuzz", numbered=True)
        check_reader(kind, data.draw(mutated_text(valid[kind])), folder)

    return run


KINDS = ["observations", "calibration", "setup"]


@pytest.mark.parametrize("kind", KINDS)
def test_fuzzed_files_read_or_give_format_error(valid, tmp_path_factory, kind):
    _fuzz(kind, FAST)(valid, tmp_path_factory)


@pytest.mark.slow
@pytest.mark.parametrize("kind", KINDS)
def test_fuzzed_files_read_or_give_format_error_many(valid, tmp_path_factory, kind):
    _fuzz(kind, SLOW)(valid, tmp_path_factory)


# --------------------------------------------------------------------------- what the fuzzer found, kept as cases


def _at(path, value):
    def mutate(doc):
        _set(doc, list(path), value)

    return mutate


FOUND = [
    # (format, document index, mutation, the field the error names)
    ("setup", 0, _at(["boards", "wall0", "cols"], 10**400), "boards.wall0.cols"),
    ("observations", 0, _at(["views", 0, "rim", 0, 1], -(10**400)), "views[0].rim[0][1]"),
    ("observations", 0, _at(["n_lasers"], 10**30), "n_lasers"),
    ("observations", 0, _at(["detection"], [1.0]), "detection"),
    ("observations", 0, _at(["detection", "dot_radius_mm"], 2.0), "detection.dot_radius_mm"),
    ("observations", 0, _at(["detection", "dot_radius_mm", "wall0"], [2.0]), "detection.dot_radius_mm.wall0"),
    ("observations", 0, _at(["detection", "spot_sigma_mm"], ""), "detection.spot_sigma_mm"),
    ("observations", 0, _at(["detection", "ambiguous_boards", 0, "view"], 7), "detection.ambiguous_boards[0].view"),
    (
        "observations",
        0,
        _at(["detection", "ambiguous_boards", 0, "candidates", 1, "indices", 2], 10**6),
        "detection.ambiguous_boards[0].candidates[1].indices[2]",
    ),
    ("observations", 0, _at(["rigid_boards", 1], [0]), "rigid_boards[1]"),
    ("observations", 0, _at(["rigid_boards", 0], "ceiling"), "rigid_boards[0]"),
    ("setup", 0, _at(["rigid_boards", 0], ["wall0"]), "rigid_boards[0]"),
    ("observations", 2, _at(["mirror_shape", "radius"], 2.68e155), "mirror_shape"),  # an asphere's
    ("observations", 0, _at(["mirror_shape", "radius"], 1e308), None),  # a wide cone: reads
    ("observations", 0, _at(["mirror_shape", "height"], 1e-310), "mirror_shape.height"),  # slope 2e311
    ("observations", 0, _at(["boards", "wall0", "points", 0, 2], 1e-300), None),  # z = 0 exactly, read
    ("calibration", 0, _at(["lasers", 1, "direction"], [1e308, 1e308, 0.0]), None),  # reads: a unit direction
    ("calibration", 0, _at(["mirror", "axis"], [0.0, -1e308, 1e308]), None),
    ("calibration", 0, _at(["residuals"], [0.3]), "residuals"),
    ("calibration", 0, _at(["residuals", "by_kind_sigma_px", "spot"], "0.3"), "residuals.by_kind_sigma_px.spot"),
    ("calibration", 0, _at(["residuals", "sigma_px"], -1.0), "residuals.sigma_px"),
    ("calibration", 0, _at(["uncertainty"], 1.0), "uncertainty"),
    ("calibration", 0, _at(["uncertainty", "covariance", "matrix", 4, 4], -1.0), "uncertainty.covariance.matrix[4][4]"),
    ("calibration", 0, _at(["uncertainty", "covariance", "matrix", 2, 5], 1.0), "uncertainty.covariance.matrix[2][5]"),
    ("calibration", 0, _at(["uncertainty", "covariance", "matrix", 3], "x"), "uncertainty.covariance.matrix[3]"),
]


@pytest.mark.parametrize("case", FOUND, ids=lambda c: f"{c[0]}-{c[3]}")
def test_what_the_fuzzer_found(valid, tmp_path, case):
    kind, k, mutate, field = case
    doc = copy.deepcopy(valid[kind][k])
    mutate(doc)
    path = tmp_path / f"{kind}.json"
    path.write_text(json.dumps(doc))
    if field is None:
        READERS[kind](path)  # reads, and its values hold the invariants
        return
    with pytest.raises(FormatError) as e:
        READERS[kind](path)
    m = MESSAGE.match(str(e.value))
    assert m is not None and m["file"] == str(path) and m["field"] == field, str(e.value)


@pytest.mark.parametrize("kind", KINDS)
def test_json_nested_too_deeply_is_a_format_error(tmp_path, kind):
    path = tmp_path / "deep.json"
    path.write_text('{"format": ' + "[" * 100_000 + "]" * 100_000 + "}")
    with pytest.raises(FormatError, match=r"deep\.json: \(file\): .*nested too deeply"):
        READERS[kind](path)
