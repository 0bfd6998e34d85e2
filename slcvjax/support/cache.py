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

A damaged entry (truncated by a process killed while writing it, garbled on disk) is
detected when it is read, deleted and compiled again, whose fresh entry takes its place;
the first in a process gives one warning (:func:`dropped_damaged`), any later one is
dropped the same way without another.  JAX alone would warn on every read of it, in every
process, and never replace it (its cache does not overwrite an entry).  A compiled entry
is zlib-compressed, whose checksum catches a garbled byte; a traced one
(:mod:`slcvjax.support.persist`) carries its own SHA-256.
"""

import logging
import os
import sys
import tempfile
import threading
import warnings
from pathlib import Path

import filelock
import jax

ENV = "SLCVJAX_CACHE_DIR"
MAX_BYTES = 4 * 2**30
LOCK_NAME = ".lockfile"  # JAX's cache lock file in the folder (``jax._src.lru_cache``)

_log = logging.getLogger("slcvjax")


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


def compile_note() -> str | None:
    """A line for a command about to calibrate where it will compile first (no traced program in
    the cache yet, or the cache off), else None."""
    folder = compilation_cache_dir()
    if folder is None:
        return "compiling (the compilation cache is off: every run compiles; about a minute)"
    traces = folder / "traces"
    if not traces.is_dir() or not any(traces.iterdir()):
        return f"compiling, once; kept in the cache ({folder}): this first run takes about a minute longer"
    return None


def enable() -> Path | None:
    """Turn the persistent compilation cache on in :func:`chosen_dir`; returns the folder (None: off),
    which :func:`compilation_cache_dir` gives from then on."""
    global _IN_USE
    _IN_USE = _enable()
    return _IN_USE


def _enable() -> Path | None:
    folder = chosen_dir()
    if folder is not None:
        _check_compiled_entries()
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


# --------------------------------------------------------------------------- damaged entries

_DAMAGED: list[str] = []  # the entries this process dropped (the first one warned)
_DAMAGED_LOCK = threading.Lock()


def dropped_damaged() -> list[str]:
    """The damaged cache entries (file paths) this process has dropped so far."""
    return list(_DAMAGED)


def forget_damaged() -> None:
    """Forget the damaged entries this process dropped (the next one warns again)."""
    with _DAMAGED_LOCK:
        _DAMAGED.clear()


def drop_damaged(paths: list[Path], why: str, again: str = "compiled") -> None:
    """Delete a damaged cache entry (its files ``paths``, the first the entry itself) under the
    folder's lock, and say so: one warning for the first in this process, an info log line (the
    ``slcvjax`` logger) for each later one.  ``again``: what the caller does instead (compiled,
    traced)."""
    entry = paths[0]
    try:
        with filelock.FileLock(entry.parent / LOCK_NAME, timeout=60):
            for p in paths:
                p.unlink(missing_ok=True)
    except (OSError, filelock.Timeout) as e:
        why += f"; it could not be deleted ({e})"
    with _DAMAGED_LOCK:
        first = not _DAMAGED
        _DAMAGED.append(str(entry))
    msg = f"slcvjax: the compilation cache entry {entry} is damaged ({why}); dropped it, {again} again"
    if first:
        warnings.warn(
            msg + " (any other damaged entry is dropped the same way without another warning)",
            RuntimeWarning,
            stacklevel=2,
        )
    else:
        _log.info(msg)


def _check_compiled_entries() -> None:
    """Wrap JAX's read of a compiled entry so that a damaged one is dropped (see the module docstring).

    JAX's own read (``jax._src.compilation_cache.get_executable_and_time``) raises on an entry that
    does not decompress or deserialize, and its caller warns and compiles without replacing the
    entry.  The wrapper deletes the entry first, so the compilation's fresh entry is written in its
    place.  Where JAX's internals are not as expected, nothing is wrapped (JAX then warns itself)."""
    try:
        from jax._src import compilation_cache as cc
    except ImportError:  # pragma: no cover
        return
    read = getattr(cc, "get_executable_and_time", None)
    if read is None or getattr(read, "_slcvjax", False):
        return

    def get_executable_and_time(cache_key, *args, **kwargs):
        try:
            return read(cache_key, *args, **kwargs)
        except filelock.Timeout:  # another process holds the folder: not damage (JAX warns)
            raise
        except Exception as e:  # noqa: BLE001  (whatever does not load is damaged)
            folder = jax.config.jax_compilation_cache_dir
            if not folder:
                raise
            entry = Path(folder) / f"{cache_key}-cache"
            drop_damaged([entry, Path(folder) / f"{cache_key}-atime"], f"{type(e).__name__}: {e}")
            return None, None

    get_executable_and_time._slcvjax = True  # type: ignore[attr-defined]
    cc.get_executable_and_time = get_executable_and_time
