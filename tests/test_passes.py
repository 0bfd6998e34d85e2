"""The joint passes of :mod:`slcvjax.calibration.passes`: :meth:`PassSpec.describe` says in words
what each field of the pass does, and the schedule's passes are the ones its docstring states."""

import dataclasses

import pytest

from slcvjax.calibration.passes import (
    PASS_A,
    PASS_A2,
    PASS_B,
    PASS_B2,
    PASS_C,
    PASS_C2,
    PASS_C3,
    RTOL_FINAL,
    STEPS_A,
    TWIN_SOLVE,
    PassSpec,
)
from slcvjax.calibration.schedule import SCHEDULE, schedule_table


def test_a_plain_pass_frees_and_weighs_everything():
    assert PassSpec("X").describe() == (
        "frees everything; weights dots 1, spots 1, rim 1, corners 1; loss scale the trial's; rtol 1e-05"
    )


@pytest.mark.parametrize(
    "change, words",
    [
        (dict(lasers_held=True), "frees everything but the lasers;"),
        (dict(rig_held=True), "frees the board poses only (the rig held);"),
        (dict(lasers_held=True, rig_held=True), "frees the board poses only (the rig held);"),
        (dict(kind_weight=(1.0, 0.0, 0.5, 2.0)), "; weights dots 1, spots 0, rim 0.5, corners 2;"),
        (dict(scale_floor=0.05), "; loss scale re-estimated (at least 0.05 px);"),
        (dict(rtol=1e-10), "; rtol 1e-10"),
        (dict(steps=7), "; at most 7 steps"),
        (dict(loss="cauchy"), "; cauchy loss"),
    ],
)
def test_each_field_is_said(change, words):
    assert words in dataclasses.replace(PassSpec("X"), **change).describe()


def test_the_schedules_passes_say_what_the_schedule_does():
    """Passes A and A2 hold the lasers and weigh the spots 0 with a step limit; B re-estimates
    the scale; the final passes converge to round-off; the other starts move the poses only."""
    for p in (PASS_A, PASS_A2):
        assert p.describe().startswith("frees everything but the lasers; weights dots 1, spots 0, rim 1, corners 1;")
        assert p.describe().endswith(f"; at most {STEPS_A} steps")
    assert "loss scale re-estimated (at least 0.05 px)" in PASS_B.describe()
    assert PASS_B2.describe() == PassSpec("X").describe()
    for p in (PASS_C, PASS_C2, PASS_C3):
        assert p.rtol == RTOL_FINAL and p.describe().endswith(f"; rtol {RTOL_FINAL:g}")
    assert TWIN_SOLVE.describe().startswith("frees the board poses only (the rig held);")


def test_the_table_lists_every_step_with_its_passes():
    table = schedule_table().splitlines()
    assert len(table) == 2 + len(SCHEDULE)
    for row, step in zip(table[2:], SCHEDULE, strict=True):
        assert step.does in row
        for p in step.passes:
            assert f"**{p.name}**: {p.describe()}" in row
