"""The records of :mod:`slcvjax.calibration.result`: a :class:`Repair` writes the calibration file's
record exactly as the dicts of the calibration did before it was typed (keys, values, order), and
reads it back."""

import json

import pytest

from slcvjax.calibration.result import Repair
from slcvjax.observations.formats import FormatError

# the records as the builders wrote them when a repair was a dict (their expressions, kept here as
# the independent truth of the key order): the lines' consensus, the outlier search (left out,
# a dot given another grid position, a spot given another laser) and pass R's board
_SPOT = {"kind": "spot", "view": "view04", "index": 0, "board": "wall0"}
_DOT = {"kind": "dot", "view": "view02", "index": 8, "board": "wall0"}
CASES = [
    (
        Repair(**_SPOT, action="relabelled", reason="lies on laser 0's line, not on its own (threshold 4.95 px)",
               residual_px=164.19418662554554, laser=1, new_laser=0, new_residual_px=0.6181766239792647,
               stage="lines"),
        _SPOT | {"action": "relabelled", "laser": 1, "residual_px": 164.19418662554554}
        | {"new_laser": 0, "new_residual_px": 0.6181766239792647}
        | {"reason": "lies on laser 0's line, not on its own (threshold 4.95 px)"},
    ),
    (
        Repair(**_SPOT, action="left out", reason="laser 1 is undetermined: its spots cannot fix a line",
               residual_px=None, laser=1, stage="lines"),
        _SPOT | {"action": "left out", "laser": 1, "residual_px": None}
        | {"reason": "laser 1 is undetermined: its spots cannot fix a line"},
    ),
    (
        Repair(**_DOT, action="left out", reason="residual 20.3 px beyond 1.43 px", residual_px=20.25535958739575),
        _DOT | {"action": "left out", "residual_px": 20.25535958739575} | {"reason": "residual 20.3 px beyond 1.43 px"},
    ),
    (
        Repair(**_SPOT, action="left out", reason="its board's pose in this view is not determined", laser=3,
               whole_board=True),
        _SPOT | {"laser": 3} | {"action": "left out", "residual_px": None}
        | {"reason": "its board's pose in this view is not determined"} | {"whole_board": True},
    ),
    (
        Repair(**_SPOT, action="left out", reason="residual 31.7 px beyond 2 px", residual_px=31.7, laser=2),
        _SPOT | {"laser": 2} | {"action": "left out", "residual_px": 31.7} | {"reason": "residual 31.7 px beyond 2 px"},
    ),
    (
        Repair(**_DOT, action="relabelled", reason="lies on grid position 5 of its board", residual_px=None,
               new_index=5, new_residual_px=0.25),
        _DOT | {"action": "relabelled", "new_index": 5, "residual_px": None} | {"new_residual_px": 0.25}
        | {"reason": "lies on grid position 5 of its board"},
    ),
    (
        Repair(**_SPOT, action="relabelled", reason="lies on laser 2's line at the final geometry, not on its own",
               residual_px=12.5, laser=1, new_laser=2, new_residual_px=0.5),
        _SPOT | {"action": "relabelled", "laser": 1} | {"residual_px": 12.5}
        | {"new_laser": 2, "new_residual_px": 0.5}
        | {"reason": "lies on laser 2's line at the final geometry, not on its own"},
    ),
    (
        Repair("board", "view03", -1, "wall2", "left out", "does not fit the rigid box", residual_px=14.25,
               whole_board=True, stage="box"),
        {"kind": "board", "view": "view03", "board": "wall2", "index": -1, "action": "left out",
         "residual_px": 14.25, "reason": "does not fit the rigid box", "whole_board": True},
    ),
    (  # a row the problem did not record (no source): no view, index -1
        Repair("dot", None, -1, "", "left out", "off the mirror"),
        {"kind": "dot", "view": None, "index": -1, "board": ""} | {"action": "left out", "residual_px": None}
        | {"reason": "off the mirror"},
    ),
]  # fmt: skip


@pytest.mark.parametrize("repair, written", CASES)
def test_a_repair_writes_the_record_byte_for_byte(repair, written):
    assert json.dumps(repair.to_json()) == json.dumps(written)


@pytest.mark.parametrize("repair, written", CASES)
def test_a_repair_reads_back_from_the_file(repair, written):
    doc = json.loads(json.dumps(written))  # as the file gives it
    back = Repair.from_json(doc)
    assert back == repair  # its stage too, from the order of its keys
    assert json.dumps(back.to_json()) == json.dumps(written)


def test_a_repair_is_immutable():
    repair = CASES[0][0]
    with pytest.raises(AttributeError):
        repair.laser = 2  # type: ignore[misc]


@pytest.mark.parametrize(
    "doc, field",
    [
        ([], r"rep: expected an object"),
        ({k: v for k, v in CASES[2][1].items() if k != "reason"}, r"rep\.reason: missing"),
        (CASES[2][1] | {"kind": "corner"}, r"rep\.kind: expected"),
        (CASES[2][1] | {"action": "moved"}, r"rep\.action: expected"),
        (CASES[2][1] | {"index": "8"}, r"rep\.index: expected a number"),
        (CASES[2][1] | {"residual_px": "big"}, r"rep\.residual_px: expected a number"),
        (CASES[0][1] | {"new_laser": True}, r"rep\.new_laser: expected a number"),
    ],
)
def test_a_bad_record_is_refused_by_name(doc, field):
    with pytest.raises(FormatError, match=field):
        Repair.from_json(doc, "rep")
