"""Studies in chunks of trials: in this process or on a Ray cluster, resumable and fault tolerant.

A study (a sweep's Monte Carlo trials, a design's confirmation) is a list of ``items``, one per
trial (its noise, its seed: small JSON values), and a **task**: a module-level function
``task(payload, items) -> records`` that simulates and calibrates a run of items and returns one
JSON-able record per item (the trial's errors, its convergence).  ``payload`` is what every trial
shares (the scene, the truth, the settings): built once, shipped once.

:func:`run_chunks` splits the items into chunks of ``chunk_size`` consecutive trials and runs the
task on each chunk, either here one after another, or each chunk as one Ray task on a cluster
(:func:`connect`).  Both paths call the same task on the same chunks, so the records are the same,
bit for bit, on the same platform (the floats travel as JSON, whose ``repr`` round-trips a float64).

With a folder, the study is resumable:

* ``study.json``, the manifest: the study's name, its settings and their hash
  (:func:`settings_hash`), the item count and the chunk size, written before the first chunk;
* ``chunks/chunk-NNNNNN.json``: each chunk's records, written by this process (the driver) as
  soon as the chunk finishes, atomically (a temporary file renamed into place), so a chunk file is
  whole or absent: a run stopped at any moment (Ctrl-C, a lost driver) leaves a folder to resume.

A later run of the same settings skips the chunks already there; a run of other settings in the
same folder is refused (:class:`StudyError`, one line) instead of mixing the two.  On a cluster, a
worker process that dies under a chunk (killed, out of memory, its node lost) has the chunk run
again elsewhere (Ray's ``max_retries``); the driver writes each chunk once, from the attempt that
finished, so nothing is lost or counted twice.  An exception raised by the task itself (a
calibration error) is not retried: it is the study's answer and stops the run.

Ray is an optional dependency (``pip install 'slcvjax[cluster]'``), imported only here and only
when a cluster is asked for.
"""

import hashlib
import json
import logging
import os
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields, is_dataclass
from pathlib import Path
from typing import Any

import jax
import numpy as np

from ..observations.formats import write_text_atomic

STUDY_FORMAT = "slcv-study/1"
MANIFEST = "study.json"
CHUNKS = "chunks"
INSTALL_HINT = "pip install 'slcvjax[cluster]'"
# the tests' hook, a folder: a file ``crash-chunk-K`` there makes the next attempt at chunk K
# delete it and kill its worker process (os._exit), as a killed worker would die; the retry runs
CRASH_ENV = "SLCVJAX_STUDY_CRASH_DIR"
MAX_RETRIES = 3  # Ray's retries of a chunk whose worker died

_log = logging.getLogger("slcvjax")


class StudyError(ValueError):
    """A study that cannot run as asked: another study's folder, nothing to resume, no Ray, a bad
    ``--cluster``.  A ``ValueError``: the command line reports its one line and exits with 2."""


# --------------------------------------------------------------------------- the cluster


@dataclass(frozen=True)
class ClusterSpec:
    """Where a study's chunks run (:func:`parse_cluster`).

    ``kind``: ``auto`` (a running cluster's address, else a local one), ``local`` (a Ray instance
    started here with ``workers`` CPUs) or ``address`` (``ray://HOST:PORT``, a running cluster's
    client address, in ``address``)."""

    kind: str
    workers: int | None = None
    address: str | None = None

    def __str__(self) -> str:
        if self.kind == "local":
            return f"local:{self.workers}"
        return self.address if self.kind == "address" else "auto"


def parse_cluster(text: str) -> ClusterSpec:
    """``auto``, ``local:N`` (N >= 1 worker processes on this machine) or ``ray://HOST:PORT``.

    Raises:
        StudyError: anything else (one line naming ``--cluster`` and the forms it takes).
    """
    text = text.strip()
    if text == "auto":
        return ClusterSpec("auto")
    if text.startswith("local:"):
        n = text[len("local:") :]
        if n.isdigit() and int(n) >= 1:
            return ClusterSpec("local", workers=int(n))
    if text.startswith("ray://"):
        host, sep, port = text[len("ray://") :].rpartition(":")
        if host and sep and port.isdigit():
            return ClusterSpec("address", address=text)
    raise StudyError(f"--cluster: expected auto, local:N (N >= 1) or ray://HOST:PORT, got {text!r}")


def require_ray():
    """The ``ray`` module.

    Raises:
        StudyError: Ray is not installed (the line names ``pip install 'slcvjax[cluster]'``).
    """
    try:
        import ray
    except ImportError:
        raise StudyError(f"--cluster needs Ray, which is not installed: {INSTALL_HINT}") from None
    return ray


def connect(spec: ClusterSpec, cache_dir: str | os.PathLike | None = None) -> tuple[Any, bool]:
    """Join (or start) the Ray cluster ``spec`` names; returns ``(ray, started)``.

    ``started`` is True where this call initialised Ray (the caller shuts it down when done); a
    process that already called ``ray.init`` keeps its own cluster (``spec`` is then not used).
    ``auto`` joins a running cluster (``ray.init(address="auto")``: the ``RAY_ADDRESS`` variable,
    else a cluster started on this machine with ``ray start --head``) and otherwise starts a local
    one with every CPU.

    ``cache_dir``: a folder every worker reaches (a shared file system) for the persistent
    compilation cache; the workers get it as ``SLCVJAX_CACHE_DIR``, so a program one of them
    compiled is loaded by the others.  None: a local cluster's workers use this process's cache
    folder; a remote cluster's workers, each their machine's own.

    Raises:
        StudyError: Ray is missing, or the cluster cannot be reached.
    """
    ray = require_ray()
    if ray.is_initialized():
        return ray, False
    from ..support.cache import compilation_cache_dir

    env = {}
    if cache_dir is not None:
        env["SLCVJAX_CACHE_DIR"] = str(Path(cache_dir).absolute())
    elif spec.kind == "local" and compilation_cache_dir() is not None:
        env["SLCVJAX_CACHE_DIR"] = str(compilation_cache_dir())
    kw: dict = {"runtime_env": {"env_vars": env}} if env else {}
    quiet = {"include_dashboard": False, "log_to_driver": False, "logging_level": logging.ERROR}
    with warnings.catch_warnings():
        # Ray starts its processes by fork + exec, which JAX warns of in a multithreaded process;
        # the exec follows at once, so no lock held by another thread is inherited
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        try:
            if spec.kind == "address":
                ray.init(address=spec.address, logging_level=logging.WARNING, **kw)
            elif spec.kind == "local":
                ray.init(num_cpus=spec.workers, **quiet, **kw)
            else:
                try:
                    ray.init(address="auto", logging_level=logging.WARNING, **kw)
                except ConnectionError:
                    ray.init(**quiet, **kw)
        except (ConnectionError, RuntimeError, ValueError) as e:
            raise StudyError(f"--cluster {spec}: cannot reach the Ray cluster: {str(e).splitlines()[0]}") from None
    global _STARTED
    _STARTED = True
    return ray, True


_STARTED = False  # whether this process started the Ray instance it is connected to (connect)


def shutdown_started(timeout_s: float = 10.0) -> None:
    """Shut down the Ray instance this process started, if any: what a command stopped by a signal
    does before it exits (a local cluster's agent processes would outlive an abrupt exit).  Runs in
    a thread and waits for it at most ``timeout_s`` seconds (a signal may have come in the middle
    of a Ray call)."""
    global _STARTED
    if not _STARTED:
        return
    _STARTED = False
    import threading

    import ray

    t = threading.Thread(target=ray.shutdown, daemon=True)
    t.start()
    t.join(timeout_s)


def _chunk_task(task: Callable, payload: Any, items: list, index: int) -> list:
    """What a Ray worker runs for chunk ``index`` (with the tests' crash hook, :data:`CRASH_ENV`)."""
    hook = os.environ.get(CRASH_ENV, "")
    if hook:
        armed = Path(hook) / f"crash-chunk-{index}"
        try:
            armed.unlink()
        except FileNotFoundError:
            pass
        else:
            os._exit(1)  # the worker dies as if killed: Ray runs the chunk again
    return task(payload, items)


# --------------------------------------------------------------------------- settings and the folder


def _canonical(x: Any) -> Any:
    """A JSON value standing for ``x``: dataclasses and pytrees by their fields and leaves, arrays by
    their dtype, shape and a SHA-256 of their bytes."""
    if isinstance(x, (str, bool, int)) or x is None:
        return x
    if isinstance(x, float):
        return repr(x)
    if isinstance(x, dict):
        return {str(k): _canonical(v) for k, v in sorted(x.items(), key=lambda kv: str(kv[0]))}
    if isinstance(x, (list, tuple)):
        return [_canonical(v) for v in x]
    if isinstance(x, (np.ndarray, np.generic, jax.Array)):
        a = np.ascontiguousarray(np.asarray(x))
        return {"dtype": str(a.dtype), "shape": list(a.shape), "sha256": hashlib.sha256(a.tobytes()).hexdigest()}
    if is_dataclass(x) and not isinstance(x, type):
        return {type(x).__name__: {f.name: _canonical(getattr(x, f.name)) for f in fields(x)}}
    leaves, tree = jax.tree_util.tree_flatten(x)
    if len(leaves) == 1 and leaves[0] is x:
        raise TypeError(f"settings: cannot fingerprint a {type(x).__name__}")
    return {"tree": str(tree), "leaves": [_canonical(v) for v in leaves]}


def settings_hash(settings: dict) -> str:
    """SHA-256 (hex) of a study's settings: JSON values, arrays, dataclasses and pytrees (a plan, a
    rig), each array by its exact bytes.  Equal settings give equal hashes in every process."""
    text = json.dumps(_canonical(settings), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def chunk_bounds(n_items: int, chunk_size: int) -> list[tuple[int, int]]:
    """``[(start, stop), ...]``: the chunks of ``n_items`` items, ``chunk_size`` each (the last one
    shorter).  Raises ``ValueError`` for a chunk size under 1."""
    if chunk_size < 1:
        raise ValueError(f"chunk size: expected at least 1, got {chunk_size}")
    return [(s, min(s + chunk_size, n_items)) for s in range(0, n_items, chunk_size)]


def _describe(settings: dict) -> dict:
    """The settings as they are written in the manifest (JSON values as they are, the rest by hash)."""
    out = {}
    for k, v in settings.items():
        try:
            json.dumps(v, allow_nan=False)
            out[k] = v
        except (TypeError, ValueError):
            out[k] = {"sha256": settings_hash({k: v})}
    return out


def _differences(old: dict, new: dict) -> str:
    """``trials 8 there, 16 now, ...``: the settings that differ (a hashed one by its hash's start)."""

    def show(v):
        return f"#{v['sha256'][:10]}" if isinstance(v, dict) and list(v) == ["sha256"] else json.dumps(v)

    keys = [k for k in dict.fromkeys([*old, *new]) if old.get(k) != new.get(k)]
    return ", ".join(f"{k} {show(old.get(k))} there, {show(new.get(k))} now" for k in keys[:4])


def _chunk_path(folder: Path, index: int) -> Path:
    return folder / CHUNKS / f"chunk-{index:06d}.json"


def _read_chunk(path: Path, index: int, items: list) -> list | None:
    """The records of a finished chunk, or None where the file is absent or is not this chunk's."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if doc.get("index") != index or doc.get("items") != items or len(doc.get("records", ())) != len(items):
        return None
    return doc["records"]


def prepare_folder(
    folder: str | os.PathLike,
    study: str,
    settings: dict,
    n_items: int,
    chunk_size: int | None,
    resume: str,
    default_chunk_size: int = 8,
) -> tuple[Path, int]:
    """Make or check a study's folder; returns ``(folder, chunk size)``.

    Args:
        folder: the study's output folder (made where absent).
        study: the study's name (``sweep``, ``design-confirm``).
        settings: what decides the study's numbers (:func:`settings_hash`).
        n_items: the number of trials.
        chunk_size: trials per chunk; None: the folder's, where it holds this study, else
            ``default_chunk_size``.
        resume: ``auto`` (resume the same settings, start a fresh folder, refuse other settings),
            ``require`` (``--resume``: the folder must hold this study) or ``restart`` (discard
            the chunks there and start again).

    Raises:
        StudyError: the folder holds a study of other settings (``auto``, ``require``), or none
            (``require``).
    """
    if resume not in ("auto", "require", "restart"):
        raise ValueError(f"resume: expected auto, require or restart, got {resume!r}")
    folder = Path(folder)
    manifest = folder / MANIFEST
    digest = settings_hash(settings)
    old = None
    if manifest.exists():
        try:
            old = json.loads(manifest.read_text(encoding="utf-8"))
        except (OSError, ValueError) as e:
            raise StudyError(f"{manifest}: cannot be read ({e}); use another folder, or --restart") from None
    if old is not None and resume != "restart":
        if old.get("format") != STUDY_FORMAT or old.get("study") != study or old.get("hash") != digest:
            what = _differences(old.get("settings", {}), _describe(settings)) if old.get("study") == study else ""
            raise StudyError(
                f"{folder} holds a {old.get('study', 'different')} study of other settings"
                + (f" ({what})" if what else "")
                + ": not mixing them; use another --out, or --restart to discard it"
            )
        if chunk_size is not None and chunk_size != old.get("chunk_size"):
            raise StudyError(
                f"{folder} holds this study in chunks of {old.get('chunk_size')} trials, not {chunk_size}: "
                "resume it without --chunk, or --restart"
            )
        return folder, int(old["chunk_size"])
    if resume == "require":
        raise StudyError(f"--resume: {folder} holds no study to resume ({manifest} is absent)")
    chunk_size = default_chunk_size if chunk_size is None else chunk_size
    if chunk_size < 1:
        raise ValueError(f"--chunk: expected at least 1 trial, got {chunk_size}")
    folder.mkdir(parents=True, exist_ok=True)
    if (folder / CHUNKS).is_dir():
        for p in (folder / CHUNKS).glob("chunk-*.json"):
            p.unlink()
    doc = {
        "format": STUDY_FORMAT,
        "study": study,
        "settings": _describe(settings),
        "hash": digest,
        "n_items": n_items,
        "chunk_size": chunk_size,
    }
    write_text_atomic(manifest, json.dumps(doc, indent=1) + "\n")
    return folder, chunk_size


# --------------------------------------------------------------------------- running


def run_chunks(
    task: Callable[[Any, list], list],
    payload: Any,
    items: Sequence,
    *,
    study: str,
    settings: dict,
    chunk_size: int | None = None,
    default_chunk_size: int = 8,
    folder: str | os.PathLike | None = None,
    resume: str = "auto",
    cluster: "str | ClusterSpec | None" = None,
    cache_dir: str | os.PathLike | None = None,
    progress: bool = False,
    desc: str = "calibrations",
    on_chunk: Callable[[int, int], None] | None = None,
) -> list:
    """Run ``task`` over ``items`` in chunks; returns one record per item, in the items' order.

    Args:
        task: a module-level function (a cluster's workers import it by name)
            ``task(payload, items[start:stop]) -> list`` of ``stop - start`` JSON-able records.
        payload: what every chunk shares (picklable); shipped to the cluster once.
        items: the trials (JSON values: a trial's noise in px, its seed), length ``n``.
        study: the study's name, in the manifest.
        settings: what decides the numbers (:func:`settings_hash`); a folder of other settings is
            refused.
        chunk_size: trials per chunk (None: the folder's, where it holds this study, else
            ``default_chunk_size``).
        folder: where the manifest and the chunks go (None: nowhere, nothing resumable).
        resume: :func:`prepare_folder`'s (``auto``, ``require``, ``restart``).
        cluster: None (this process, chunk after chunk), a :class:`ClusterSpec` or its text
            (:func:`parse_cluster`): each chunk one Ray task, one CPU (one GPU where the cluster
            has GPUs), retried up to :data:`MAX_RETRIES` times where its worker dies.
        cache_dir: a shared compilation-cache folder for the workers (:func:`connect`).
        progress: one bar over the trials (rate and time left), advanced as chunks finish.
        desc: the bar's label.
        on_chunk: called as ``on_chunk(index, done)`` after chunk ``index`` is written (``done``:
            trials finished so far, resumed ones included).

    Returns:
        The ``n`` records, ``records[i]`` the task's record of ``items[i]``.

    Raises:
        StudyError: see :func:`prepare_folder`, :func:`connect`.
        Exception: the task's own exception from the first chunk that raised it (the chunks
            written before it stay, for a later run to resume).
    """
    items = list(items)
    if folder is not None:
        folder, chunk_size = prepare_folder(folder, study, settings, len(items), chunk_size, resume, default_chunk_size)
    elif chunk_size is None:
        chunk_size = default_chunk_size
    bounds = chunk_bounds(len(items), chunk_size)
    records: dict[int, list] = {}
    if folder is not None:
        for k, (a, b) in enumerate(bounds):
            got = _read_chunk(_chunk_path(folder, k), k, items[a:b])
            if got is not None:
                records[k] = got
        if records:
            _log.info(f"{folder}: resuming: {len(records)} of {len(bounds)} chunks finished before")
    todo = [k for k in range(len(bounds)) if k not in records]
    done = sum(bounds[k][1] - bounds[k][0] for k in records)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(items), initial=done, desc=desc, unit="trial", smoothing=0.1)

    def finished(k: int, recs: list) -> None:
        nonlocal done
        a, b = bounds[k]
        if len(recs) != b - a:
            raise RuntimeError(f"chunk {k}: the task returned {len(recs)} records for {b - a} trials")
        records[k] = recs
        if folder is not None:
            doc = {"index": k, "start": a, "stop": b, "items": items[a:b], "records": recs}
            write_text_atomic(_chunk_path(folder, k), json.dumps(doc, allow_nan=True) + "\n")
        done += b - a
        if bar is not None:
            bar.update(b - a)
        if on_chunk is not None:
            on_chunk(k, done)

    try:
        if folder is not None:
            (folder / CHUNKS).mkdir(exist_ok=True)
        if cluster is None:
            for k in todo:
                a, b = bounds[k]
                finished(k, task(payload, items[a:b]))
        elif todo:
            _run_on_ray(task, payload, items, bounds, todo, cluster, cache_dir, finished)
    finally:
        if bar is not None:
            bar.close()
    return [r for k in range(len(bounds)) for r in records[k]]


def _result(ray, ref, k: int, bounds: tuple[int, int]) -> list:
    """Chunk ``k``'s records; the task's own exception as it was raised (not Ray's wrapper), and a
    chunk Ray gave up on (its workers died ``MAX_RETRIES + 1`` times) as one line."""
    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError as e:
        cause = getattr(e, "cause", None)
        if isinstance(cause, BaseException):
            raise cause from None
        raise
    except ray.exceptions.RayError as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else ""
        raise StudyError(
            f"chunk {k} (trials {bounds[0]} to {bounds[1] - 1}) failed on the cluster: {type(e).__name__}: {first}; "
            "the chunks finished before are kept: run the command again to resume"
        ) from None


def _run_on_ray(task, payload, items, bounds, todo, cluster, cache_dir, finished) -> None:
    """Each chunk of ``todo`` one Ray task; ``finished(k, records)`` as each one ends (ray.wait)."""
    spec = parse_cluster(cluster) if isinstance(cluster, str) else cluster
    ray, started = connect(spec, cache_dir)
    try:
        gpus = ray.cluster_resources().get("GPU", 0)
        resources = {"num_gpus": 1} if gpus > 0 else {"num_cpus": 1}
        remote = ray.remote(_chunk_task).options(max_retries=MAX_RETRIES, retry_exceptions=False, **resources)
        ref = ray.put(payload)
        t0 = time.perf_counter()
        pending = {remote.remote(task, ref, items[bounds[k][0] : bounds[k][1]], k): k for k in todo}
        _log.debug(f"{len(pending)} chunks submitted to the cluster ({ray.cluster_resources()})")
        try:
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1)
                for r in ready:
                    k = pending.pop(r)
                    finished(k, _result(ray, r, k, bounds[k]))
        except BaseException:
            for r in pending:
                ray.cancel(r, force=True)
            raise
        _log.debug(f"cluster: {len(todo)} chunks in {time.perf_counter() - t0:.1f} s")
    finally:
        if started:
            shutdown_started()
