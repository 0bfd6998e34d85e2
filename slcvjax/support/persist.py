"""Traced programs kept on disk: a new process skips tracing as the compilation cache skips compiling.

JAX's persistent compilation cache (:mod:`slcvjax.support.cache`) saves XLA's work, but a new process
still traces and lowers every function before it can look the compilation up, and the
joint solve takes seconds to trace.  :class:`PersistentJit` wraps a function like
``jax.jit``; the first call for a signature (the argument pytree with its static fields,
the shapes and dtypes of its arrays) exports the traced program (:func:`jax.export.export`)
to ``<cache folder>/traces/``, and a later process deserializes it and calls it
(``jax.jit(exported.call)``), whose compilation the compilation cache then holds.

An entry's name hashes the signature with the package's source code and the versions of
JAX and jaxlib, so a changed ``slcvjax`` or JAX never loads an old program.  Where the
cache is off, or exporting fails, the function is an ordinary ``jax.jit``.

An entry is ``MAGIC``, the SHA-256 of its payload, then the payload (a pickle of the
serialized program and its output's structure), written beside its place and renamed into
it.  One whose digest does not match (truncated, garbled), or that does not load, is
damaged: it is deleted with one warning (:func:`slcvjax.support.cache.drop_damaged`) and
traced again.  Without the digest a garbled program could deserialize and fail only when
called, or run with a changed constant.
"""

import hashlib
import pickle
import tempfile
import threading
from pathlib import Path

import jax
import jax.numpy as jnp
import jaxlib
import numpy as np

from .cache import compilation_cache_dir, drop_damaged

STATS = {"exported": 0, "loaded": 0}
# Programs with loops run one at a time: two executed at once from threads
# (``calibrate_many(..., workers=2)``) wedged XLA's CPU thread pool for good in
# ``benchmarks/bench_calibrate.py`` (every thread waiting on its result, no CPU used).
_EXECUTE = threading.Lock()
_SOURCE_HASH: list[str] = []


def _source_hash() -> str:
    if not _SOURCE_HASH:
        h = hashlib.sha256()
        for p in sorted(Path(__file__).parent.parent.rglob("*.py")):
            h.update(p.name.encode())
            h.update(p.read_bytes())
        h.update(f"{jax.__version__} {jaxlib.__version__} {jax.default_backend()}".encode())
        h.update(str(jax.config.jax_enable_x64).encode())
        _SOURCE_HASH.append(h.hexdigest())
    return _SOURCE_HASH[0]


def _dtype(x):
    return x.dtype if hasattr(x, "dtype") else np.result_type(x)


def committed(tree):
    """``tree`` with every leaf a strongly typed array committed to the default device.

    ``jax.jit`` compiles one program for host arrays, Python scalars or weakly typed arrays
    and another for committed device arrays of the same shapes (the trace is shared, the
    lowered program is not): a compiled entry point that receives both, say a calibration's
    host arrays and then a device result, passes its arguments through this first."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    return jax.tree_util.tree_unflatten(treedef, _committed_leaves(leaves))


def _committed_leaves(leaves: list) -> list:
    device = jax.devices()[0]
    one_device = {device}

    def one(x):
        if not isinstance(x, jax.Array):  # host: straight to the device
            return jax.device_put(np.asarray(x, dtype=_dtype(x)), device)
        if x.weak_type:  # strongly typed, of its dtype
            return jax.device_put(jnp.asarray(x, dtype=x.dtype), device)
        return x if x.committed and x.sharding.device_set == one_device else jax.device_put(x, device)

    return [one(x) for x in leaves]


def _folder() -> Path | None:
    d = compilation_cache_dir()
    return None if d is None else Path(d) / "traces"


MAGIC = b"slcvjax-trace/1\n"


def _write_atomic(path: Path, data: bytes) -> None:
    with tempfile.NamedTemporaryFile(dir=path.parent, prefix=".tmp-", delete=False) as f:
        try:
            f.write(data)
        except BaseException:
            f.close()
            Path(f.name).unlink(missing_ok=True)
            raise
    Path(f.name).replace(path)


def _frame(payload: bytes) -> bytes:
    return MAGIC + hashlib.sha256(payload).digest() + payload


def unframe(data: bytes) -> bytes:
    """The payload of an entry; ValueError where it is damaged."""
    n = len(MAGIC)
    if data[:n] != MAGIC:
        raise ValueError("not an slcvjax trace entry (header)" if data else "empty file")
    digest, payload = data[n : n + 32], data[n + 32 :]
    if hashlib.sha256(payload).digest() != digest:
        raise ValueError(f"checksum mismatch over {len(data)} bytes (truncated or garbled)")
    return payload


class PersistentJit:
    """``jax.jit(fn)`` whose traced program persists across processes (see the module docstring).

    Positional array arguments only (pytrees of arrays); no static arguments.
    """

    def __init__(self, fn, name: str):
        self.fn, self.name = fn, name
        self.jit = jax.jit(fn)
        self._calls: dict = {}

    def signatures(self) -> int:
        """How many argument signatures (each its own program) this process has called it with."""
        return len(self._calls)

    def clear(self) -> None:
        """Forget the programs this process holds (those on disk stay)."""
        self._calls.clear()

    def __call__(self, *args):
        # Python scalars, weakly typed or uncommitted arrays would make one exported signature
        # several compilations
        leaves, tree = jax.tree_util.tree_flatten(args)
        leaves = _committed_leaves(leaves)
        sig = (tree, tuple((x.shape, x.dtype) for x in leaves))
        entry = self._calls.get(sig)
        if entry is None:
            entry = self._calls[sig] = self._entry(leaves, tree, sig)
        with _EXECUTE:
            if entry is False:  # uncached: committed arguments too, or one signature compiles twice
                return jax.block_until_ready(self.jit(*jax.tree_util.tree_unflatten(tree, leaves)))
            call, out_tree = entry
            return jax.tree_util.tree_unflatten(out_tree, jax.block_until_ready(call(*leaves)))

    def _entry(self, leaves, tree, sig):
        folder = _folder()
        if folder is None:
            return False
        text = (str(tree), tuple((shape, str(dtype)) for shape, dtype in sig[1]))
        key = hashlib.sha256(f"{self.name} {text} {_source_hash()}".encode()).hexdigest()[:40]
        path = folder / f"{self.name}-{key}.jaxexport"
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            data = None
        except OSError as e:  # unreadable: traced again, and written over below
            data = None
            drop_damaged([path], f"cannot be read: {e}", "traced")
        if data is not None:
            try:
                blob = pickle.loads(unframe(data))
                exported = jax.export.deserialize(bytearray(blob["exported"]))
                out_tree = jax.tree_util.tree_structure(pickle.loads(blob["skeleton"]))
                STATS["loaded"] += 1
                return self._jit(exported), out_tree
            except Exception as e:  # noqa: BLE001  (a damaged entry is dropped and traced again)
                drop_damaged([path], f"{type(e).__name__}: {e}", "traced")
        box = []

        def flat(*xs):
            out = self.fn(*jax.tree_util.tree_unflatten(tree, list(xs)))
            out_leaves, out_tree = jax.tree_util.tree_flatten(out)
            box.append(out_tree)
            return out_leaves

        try:
            exported = jax.export.export(jax.jit(flat))(*(jax.ShapeDtypeStruct(x.shape, x.dtype) for x in leaves))
            out_tree = box[-1]
            skeleton = jax.tree_util.tree_unflatten(out_tree, [0] * out_tree.num_leaves)
            blob = {"exported": bytes(exported.serialize()), "skeleton": pickle.dumps(skeleton)}
            folder.mkdir(parents=True, exist_ok=True)
            _write_atomic(path, _frame(pickle.dumps(blob)))
        except Exception:  # noqa: BLE001  (whatever cannot be exported runs as a plain jit)
            return False
        STATS["exported"] += 1
        return self._jit(exported), out_tree

    def _jit(self, exported):
        """``jax.jit`` of the exported program under this function's name (JAX's compile log and
        profiles name a program by its function)."""

        def call(*xs):
            return exported.call(*xs)

        call.__name__ = call.__qualname__ = self.name
        return jax.jit(call)
