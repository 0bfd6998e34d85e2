"""The README and the documentation site stay true to the project: the README's quick start is the
command CI runs, and every link in the README reaches a file of the repository.  (CI builds the
site itself with ``mkdocs build --strict``, which checks the links between its pages.)"""

import re
from pathlib import Path

ROOT = Path(__file__).parent.parent
README = (ROOT / "README.md").read_text()


def test_the_readme_starts_with_the_quick_start_and_its_test_command_is_cis():
    lines = README.splitlines()
    assert lines[0] == "# slcvjax" and lines[2] == "## Quick start"  # the title, then the quick start
    quick = README.split("\n## ", 2)[1]
    blocks = re.findall(r"```bash\n(.*?)\n```", quick, flags=re.S)
    assert blocks == [
        "python3 -m venv .venv && .venv/bin/pip install -e '.[test]' && .venv/bin/slcvjax demo",
        ".venv/bin/python -m pytest",
    ]
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert "python3 -m venv .venv && .venv/bin/pip install -e '.[test]'" in ci
    assert ".venv/bin/python -m pytest" in ci
    # the site is built, strictly, before the tests run
    build = [i for i, line in enumerate(ci) if line.startswith(".venv/bin/mkdocs build --strict")]
    assert build and build[0] < ci.index(".venv/bin/python -m pytest")
    assert not [line for line in lines if line.startswith(("pytest", "python -m pytest"))]
    assert len(lines) <= 150


def test_every_link_in_the_readme_reaches_a_file():
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", README)
    assert targets
    missing = [t for t in targets if not t.startswith("http") and not (ROOT / t).exists()]
    assert not missing, missing


def test_the_readme_images_are_small():
    for target in re.findall(r"!\[[^]]*\]\(([^)]+)\)", README):
        assert (ROOT / target).stat().st_size < 300_000, target
