"""The ``slcvjax`` command line: one module per command here, each imported when its command runs.

The parser and the entry point live in the small top-level package ``slcvjax_cli``, which imports
nothing of the library: ``slcvjax --help`` and ``slcvjax --version`` answer without importing JAX.
"""

from slcvjax_cli import build_parser, configure_logging, main, stop_on_signals

__all__ = ["build_parser", "configure_logging", "main", "stop_on_signals"]
