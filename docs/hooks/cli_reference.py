"""MkDocs hook: the CLI reference page (``cli.md``), generated from the parser at every build.

Each command's ``--help`` is rendered as the parser prints it, so the page cannot fall behind the
code.  The parser (:mod:`slcvjax_cli`) imports nothing of the library, so this costs no JAX import.
"""

import argparse
import os

from mkdocs.structure.files import File

INTRO = """# CLI reference

Every command of `slcvjax`, as its `--help` prints it (this page is generated from the parser when the
site is built). Every command also takes `-q` (only warnings and errors) and `-v` (debug lines);
`slcvjax --version` prints the version. Bad input exits with status 2 and one line naming the file,
the field and the index; outputs are written atomically.
"""


def render() -> str:
    """The page's Markdown: the top-level help, then one section per command."""
    os.environ["COLUMNS"] = "100"  # argparse wraps to the terminal's width: fix it for a stable page
    from slcvjax_cli import build_parser

    parser = build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    parts = [INTRO, "## slcvjax\n", "```text\n" + parser.format_help().rstrip() + "\n```\n"]
    for name, command in sub.choices.items():
        parts.append(f"## slcvjax {name}\n")
        parts.append("```text\n" + command.format_help().rstrip() + "\n```\n")
    return "\n".join(parts)


def on_files(files, config):
    files.append(File.generated(config, "cli.md", content=render()))
    return files
