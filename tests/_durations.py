"""Write ``tests/durations.json`` from a compile log: each test file's seconds in that run.

``SLCVJAX_TEST_COMPILE_LOG=LOG python -m pytest`` (an empty compilation cache, the default two
workers), then ``python -m tests._durations LOG``.  ``tests/conftest.py`` hands the files to the
workers longest first, so that no long file is left for the end while the other worker idles.
"""

import json
import sys
from collections import Counter
from pathlib import Path


def main(log: str) -> None:
    seconds: Counter = Counter()
    for line in Path(log).read_text().splitlines():
        row = json.loads(line)
        seconds[row["test"].split("::")[0]] += row["seconds"]
    doc = {
        "about": "seconds per test file in a full run (2 workers, empty cache), from tests/_durations.py",
        "seconds": {f: round(s, 1) for f, s in sorted(seconds.items(), key=lambda kv: -kv[1])},
    }
    out = Path(__file__).with_name("durations.json")
    out.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"{out}: {len(seconds)} files, {sum(seconds.values()):.0f} s")


if __name__ == "__main__":
    main(sys.argv[1])
