"""The formulation page's generated tables are the code's: the robust policy and the pass schedule."""

import re
import sys
from pathlib import Path

from slcvjax.calibration.options import policy_table
from slcvjax.calibration.schedule import schedule_table

PAGE = Path(__file__).parent.parent / "docs" / "formulation.md"
TABLES = {"policy_table": policy_table, "schedule_table": schedule_table}


def _region(text: str, name: str) -> re.Match:
    m = re.search(rf"(<!-- BEGIN {name}[^\n]*-->\n)(.*?)(<!-- END {name} -->)", text, re.S)
    assert m, f"docs/formulation.md has no {name} region"
    return m


def test_the_pages_tables_are_generated_from_the_code():
    text = PAGE.read_text()
    for name, make in TABLES.items():
        assert _region(text, name).group(2) == make(), (
            f"docs/formulation.md's {name} differs from the code: run python tests/test_formulation.py to write it"
        )


if __name__ == "__main__":  # rewrite the page's tables from the code
    text = PAGE.read_text()
    for name, make in TABLES.items():
        m = _region(text, name)
        text = text[: m.start(2)] + make() + text[m.end(2) :]
    PAGE.write_text(text)
    sys.exit(0)
