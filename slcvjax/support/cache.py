"""The persistent compilation cache: compiled XLA programs kept on disk across processes.

A calibration compiles a few programs per shape bucket (:mod:`slcvjax.observations.problem`); kept on disk,
a later process loads them instead of compiling again.  Importing ``slcvjax`` turns the
cache on (:func:`enable`), in the first folder of:

1. ``SLCVJAX_CACHE_DIR`` (``off`` turns the cache off);
2. the folder JAX was already given (``JAX_COMPILATION_CACHE_DIR`` or
   ``jax.config.jax_compilation_cache_dir``), with JAX's settings left as they are;
3. the platform's user cache folder: ``$XDG_CACHE_HOME/slcvjax`` (else
   ``~/.cache/slcvjax``) on Linux, ``~/Library/Caches/slcvjax`` on macOS,
   ``%LOCALAPPDATA%\\slcvjax\\cache`` on Windows.

Every compilation is kept, the short ones too, up to ``MAX_BYTES`` (the least recently
used entries go first).  Several processes may share a folder at once: with a size limit
JAX reads and writes the entries under a file lock (the ``filelock`` package), so no
process reads an entry another is still writing.  A folder that cannot be written gives
one warning and the process runs uncached.
"""

import os
import sys
import tempfile
import warnings
from pathlib import Path

import jax

ENV = "SLCVJAX_CACHE_DIR"
MAX_BYTES = 4 * 2**30


def default_dir() -> Path:
    """The platform's user cache folder for slcvjax (see the module docstring)."""
    if sys.platform == "darwin":
        return Path.home() / "Library" / "Caches" / "slcvjax"
    if os.name == "nt":
        return Path(os.environ.get("LOCALAPPDATA", Path.home() / "AppData" / "Local")) / "slcvjax" / "cache"
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "slcvjax"


def chosen_dir() -> Path | None:
    """The folder :func:`enable` uses, or None where the cache is off."""
    value = os.environ.get(ENV, "").strip()
    if value.lower() == "off":
        return None
    if value:
        return Path(value).expanduser()
    if jax.config.jax_compilation_cache_dir:
        return Path(jax.config.jax_compilation_cache_dir)
    return default_dir()


def _jax_own() -> bool:
    """Whether the folder is JAX's own setting (then JAX's other cache settings are the user's too)."""
    return not os.environ.get(ENV, "").strip() and bool(jax.config.jax_compilation_cache_dir)


def _writable(folder: Path) -> str | None:
    """None where ``folder`` exists (made if need be) and takes a file; else why not."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".probe-"):
            pass
    except OSError as e:
        return e.strerror or str(e)
    return None


_IN_USE: Path | None = None


def compilation_cache_dir() -> Path | None:
    """The folder of the persistent compilation cache in use (a ``pathlib.Path``), or None where it is off."""
    return _IN_USE


def enable() -> Path | None:
    """Turn the persistent compilation cache on in :func:`chosen_dir`; returns the folder (None: off),
    which :func:`compilation_cache_dir` gives from then on."""
    global _IN_USE
    _IN_USE = _enable()
    return _IN_USE


def _enable() -> Path | None:
    folder = chosen_dir()
    if folder is not None and _jax_own():
        return folder
    if folder is None:
        jax.config.update("jax_enable_compilation_cache", False)
        return None
    why = _writable(folder)
    if why is not None:
        warnings.warn(
            f"slcvjax: the compilation cache folder {folder} cannot be written ({why}); running uncached "
            f"(set {ENV} to another folder, or to off)",
            RuntimeWarning,
            stacklevel=2,
        )
        jax.config.update("jax_enable_compilation_cache", False)
        return None
    jax.config.update("jax_enable_compilation_cache", True)
    jax.config.update("jax_compilation_cache_dir", str(folder))
    # every compilation is worth keeping: a calibration is a few large ones and many small
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
    return folder
