"""The file formats' JSON Schemas (slcvjax.observations.schemas): valid draft 2020-12 schemas,
shipped with the package, describing every field, and refusing broken documents by the field.

The documents the project writes in the other tests are checked against them by the hook in
``tests/conftest.py``; here, documents made without a calibration (fast)."""

import copy
import json
from pathlib import Path

import pytest
from jsonschema import Draft202012Validator

from slcvjax.observations import schemas
from slcvjax.observations.formats import FormatError, calibration_to_json, observations_to_json
from slcvjax.observations.simulate import make_scene, simulate
from tests.conftest import schema_problems

SCHEMA_DIR = Path(schemas.__file__).parent


@pytest.fixture(scope="module")
def simulated():
    obs, truth = simulate(make_scene(n_lasers=4, n_views=3), noise=0.3, seed=5)
    return observations_to_json(obs), calibration_to_json(truth)


def _setup_doc():
    from slcvjax.images.detect import setup_to_json
    from slcvjax.images.targetbox import box_setup

    setup, _ = box_setup(20.0, 10.0, 6, target="charuco-box")
    return setup_to_json(setup)


def test_every_schema_is_valid_and_shipped():
    files = sorted(p.name for p in SCHEMA_DIR.glob("*.schema.json"))
    assert files == sorted(name.replace("/", "-") + ".schema.json" for name in schemas.FORMATS + ("common",))
    for name in schemas.FORMATS + ("common",):
        doc = schemas.schema(name)
        Draft202012Validator.check_schema(doc)
        assert doc["$schema"] == "https://json-schema.org/draft/2020-12/schema"
        assert doc["$id"] == f"urn:slcvjax:schema:{name}"
        if name != "common":
            assert doc["properties"]["format"]["const"] == name
    with pytest.raises(KeyError, match="slcv-observations/1"):
        schemas.schema("slcv-observations/2")


def _described(sub: dict, doc: dict) -> bool:
    """Whether a property's schema has a description, or refers to a definition that has one."""
    if "description" in sub:
        return True
    ref = sub.get("$ref")
    if ref is None:
        return False
    name, _, pointer = ref.partition("#")
    doc = schemas.schema(name.removeprefix("urn:slcvjax:schema:")) if name else doc
    target = doc
    for part in filter(None, pointer.split("/")):
        target = target[part]
    return _described(target, doc)


def _fields(node, doc, where="", out=None):
    """Every property the schema declares -> whether it is described."""
    out = {} if out is None else out
    if isinstance(node, dict):
        for key, sub in (node.get("properties") or {}).items():
            out[f"{where}.{key}"] = _described(sub, doc)
        for key, sub in node.items():
            if key in ("if", "then", "else", "not"):  # conditions on fields described where they are declared
                continue
            _fields(sub, doc, where if key == "properties" else f"{where}.{key}", out)
    elif isinstance(node, list):
        for sub in node:
            _fields(sub, doc, where, out)
    return out


def test_every_field_is_described():
    """Each property has a description, or refers to a definition that has one."""
    undescribed = []
    for name in schemas.FORMATS + ("common",):
        doc = schemas.schema(name)
        fields = _fields(doc, doc)
        assert len(fields) > 5, name
        undescribed += [f"{name}{f}" for f, ok in fields.items() if not ok]
    assert not undescribed, undescribed


def test_simulated_documents_validate(simulated):
    obs, truth = simulated
    assert schemas.errors(obs) == []
    assert schemas.errors(truth) == []
    assert truth["calibration_view_poses"] and obs["rigid_boards"]  # the simulator's extra fields are there
    schemas.validate(_setup_doc(), "setup.json")


def test_the_units_are_in_the_descriptions():
    text = "".join(schemas.schema_text(n) for n in schemas.FORMATS + ("common",))
    for unit in ("(mm)", "(px)", "(deg)", "(s)"):
        assert unit in text, unit


@pytest.mark.parametrize(
    "fmt, edit, where, words",
    [
        ("obs", lambda d: d["views"][1]["spots"][0].update(laser=1.5), "views[1].spots[0].laser", "integer"),
        ("obs", lambda d: d["views"][0]["spots"][2].pop("pixel"), "views[0].spots[2]", "'pixel' is a required"),
        ("obs", lambda d: d["boards"]["wall0"]["points"][3].__setitem__(2, 1.0), "boards.wall0.points[3][2]", "1e-09"),
        ("obs", lambda d: d.update(image_size=[640]), "image_size", "too short"),
        ("obs", lambda d: d["mirror_shape"].pop("height"), "mirror_shape", "'height' is a required"),
        ("obs", lambda d: d.update(camera_projection="fisheye"), "camera_projection", "fisheye"),
        ("obs", lambda d: d.update(units="cm"), "units", "'mm' was expected"),
        ("cal", lambda d: d["camera"]["K"][2].pop(), "camera.K[2]", "too short"),
        ("cal", lambda d: d["lasers"][2].update(direction="up"), "lasers[2].direction", "'up'"),
        ("cal", lambda d: d["board_poses"][1]["wall0"].pop("R"), "board_poses[1].wall0", "'R' is a required"),
        ("cal", lambda d: d["mirror"].update(kind="torus"), "mirror.kind", "torus"),
        ("cal", lambda d: d.update(residuals={"per_view_rms_px": {}}), "residuals", "'rms_px' is a required"),
        ("setup", lambda d: d["boards"]["wall1"].update(square_mm=-18.0), "boards.wall1.square_mm", "minimum"),
        ("setup", lambda d: d["boards"]["wall0"].update(dictionary="DICT_9X9_1"), "boards.wall0.dictionary", "9X9"),
        ("setup", lambda d: d["boards"]["wall2"].update(x_dir=0), "boards.wall2.x_dir", "0 is not one of"),
        ("setup", lambda d: d.update(mirror_shape={"kind": "paraboloid"}), "mirror_shape.kind", "'cone' was expected"),
    ],
)
def test_broken_documents_are_refused_by_the_field(simulated, fmt, edit, where, words):
    doc = copy.deepcopy({"obs": simulated[0], "cal": simulated[1]}.get(fmt) or _setup_doc())
    schemas.validate(doc, "f.json")  # whole, it passes
    edit(doc)
    with pytest.raises(FormatError) as e:
        schemas.validate(doc, "f.json")
    assert str(e.value).startswith(f"f.json: {where}: "), str(e.value)
    assert words in str(e.value)


def test_a_wrong_format_is_named():
    with pytest.raises(FormatError, match=r"^x.json: format: expected one of slcv-observations/1, .*slcv-obs/1"):
        schemas.validate({"format": "slcv-obs/1"}, "x.json")
    with pytest.raises(FormatError, match=r"^x.json: format: 'slcv-points/1' was expected"):
        schemas.validate({"format": "slcv-sweep/1", "views": []}, "x.json", "slcv-points/1")


def test_extra_fields_and_nulls_are_allowed(simulated):
    obs, truth = copy.deepcopy(simulated)
    obs["my_notes"] = {"anything": [1, "two"]}
    obs["views"][0]["spots"][0]["board"] = None  # a spot whose board is not known
    obs["views"][0]["boards"]["wall0"][0] = None  # a dot not seen
    truth["lasers"][1] = {"point": None, "direction": None, "status": "undetermined: ..."}
    truth["calibration_view_poses"][0] = None
    assert schemas.errors(obs) == [] and schemas.errors(truth) == []


def test_typed_boards(simulated):
    obs = copy.deepcopy(simulated[0])
    obs["boards"]["tags"] = {"type": "aprilgrid", "tag_cols": 6, "tag_rows": 2, "tag_mm": 18.0, "spacing": 0.3}
    obs["boards"]["chess"] = {"type": "chessboard", "inner": [9, 6], "square_mm": 20.0}
    assert schemas.errors(obs) == []
    obs["boards"]["tags"]["spacing"] = 1.5  # Kalibr's spacing is in (0, 1]
    obs["boards"]["chess"].pop("square_mm")
    assert [w for w, _ in schemas.errors(obs)] == ["boards.chess", "boards.tags.spacing"]
    obs["boards"]["dots"] = {"cols": 3}  # a dots board needs its points
    assert "boards.dots" in [w for w, _ in schemas.errors(obs)]


def test_the_hook_finds_a_broken_written_file(tmp_path, simulated):
    """The conftest hook's check: a written file of a known format that does not match its
    schema is named with its field; other JSON files and hand-broken inputs that the reader
    refuses too are passed over."""
    (tmp_path / "points.json").write_text(json.dumps({"format": "slcv-points/1", "views": [{"name": "v"}]}))
    (tmp_path / "other.json").write_text(json.dumps({"format": "someone-else/3", "x": 1}))
    (tmp_path / "plain.json").write_text("[1, 2]")
    broken = copy.deepcopy(simulated[0])
    broken["n_lasers"] = -1  # an input a reader test would write: read_observations refuses it too
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "obs.json").write_text(json.dumps(broken))
    problems = schema_problems(tmp_path)
    assert problems == [f"{tmp_path / 'points.json'}: views[0]: 'points' is a required property (and 1 more)"]
    assert schema_problems(tmp_path) == []  # checked once per version of a file
    (tmp_path / "points.json").write_text(json.dumps({"format": "slcv-points/1", "views": []}) + " ")
    assert schema_problems(tmp_path) == []
