import os
from pathlib import Path

# one persistent compilation cache for the test processes (two xdist workers, the notebooks'
# kernels), apart from the user's: a computation compiled in one is loaded by the others
os.environ.setdefault("SLCVJAX_CACHE_DIR", str(Path(__file__).parent.parent / ".pytest_cache" / "jax"))
# two CPU devices in every test process and the ones they start (the count is part of every
# compilation's cache key): calibrate_many's trial axis is sharded over them in-process
os.environ.setdefault("JAX_NUM_CPU_DEVICES", "2")


def _classic_cpu_emitters() -> None:
    """The suite is compile-bound: with XLA's classic CPU emitters instead of its fusion emitters
    it compiles about 40 % faster and runs about 20 % slower (jaxlib 0.10: tests/test_implicit.py
    and tests/test_conic.py with an empty cache, one process, 200 -> 148 s).  The library keeps
    XLA's defaults (a calibration's steps run faster there).  Set for the test processes and the
    ones they start, only on the jaxlib it was measured on: XLA aborts on a flag it does not know."""
    from importlib.metadata import version

    flags = os.environ.get("XLA_FLAGS", "")
    if version("jaxlib").split(".")[:2] == ["0", "10"] and "xla_cpu_use_fusion_emitters" not in flags:
        os.environ["XLA_FLAGS"] = (flags + " --xla_cpu_use_fusion_emitters=false").strip()


_classic_cpu_emitters()

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import slcvjax  # noqa: E402, F401  (enables float64)

jax.config.update("jax_numpy_dtype_promotion", "strict")


def pytest_configure(config):
    from hypothesis import settings

    settings.register_profile("slcv", deadline=None, max_examples=40, derandomize=True)
    settings.load_profile("slcv")


def pytest_collection_modifyitems(config, items):
    """The test files longest first (``tests/durations.json``, a measured run's seconds; files it
    does not list last): xdist hands each worker the next file in this order as it runs out, so
    the run does not end on a long file while the other worker idles."""
    import json

    path = Path(__file__).with_name("durations.json")
    seconds = json.loads(path.read_text())["seconds"] if path.exists() else {}
    items.sort(key=lambda item: -seconds.get(item.nodeid.split("::")[0], 0.0))


# SLCVJAX_TEST_COMPILE_LOG=FILE: append one JSON line per test with its wall seconds, worker and start, and what JAX
# compiled during it (count, backend-compile and trace seconds), to find where the suite's time goes
_COMPILE_LOG = os.environ.get("SLCVJAX_TEST_COMPILE_LOG")
_compiled = {"n": 0, "compile": 0.0, "trace": 0.0}
_programs: list = []  # (seconds, name) of each backend compilation
if _COMPILE_LOG:

    def _listen(event, duration, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            _compiled["n"] += 1
            _compiled["compile"] += duration
            _programs.append((duration, kw.get("fun_name", "?")))
        elif event == "/jax/core/compile/jaxpr_trace_duration":
            _compiled["trace"] += duration

    jax.monitoring.register_event_duration_secs_listener(_listen)

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(item, nextitem):
        import json
        import time

        before, t0, start = dict(_compiled), time.perf_counter(), time.time()
        _programs.clear()
        yield
        row = {"test": item.nodeid, "seconds": round(time.perf_counter() - t0, 2)}
        # which process ran it and when (epoch seconds), to see how the workers shared the files
        row.update(worker=os.environ.get("PYTEST_XDIST_WORKER", "main"), start=round(start, 2))
        row.update({k: round(_compiled[k] - before[k], 2) for k in _compiled})
        row["slowest"] = [[name, round(sec, 2)] for sec, name in sorted(_programs, reverse=True)[:5]]
        with open(_COMPILE_LOG, "a") as f:
            f.write(json.dumps(row) + "\n")


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


# Every compiled program maps its code into the process, and a worker that runs many test files
# holds thousands of them.  Past this many mappings, half of Linux's default vm.max_map_count
# (65530), a test file's end drops them.  With none dropped, the whole suite (2 workers, empty
# cache) ended at 32 041 mappings and 5.0 GB resident in a worker at most, one file adding at
# most 6 400.
MAX_MAPPINGS = 32_768


def _mappings() -> int | None:
    """The process's memory mappings (None where /proc is not there to count them)."""
    try:
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f)
    except OSError:
        return None


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """After a test file, drop the process's compiled programs and traces (they stay in the
    persistent cache) once its mappings pass :data:`MAX_MAPPINGS`, or always where they cannot
    be counted.  Kept below that, the next files use them as they are instead of loading them
    from the cache and tracing their functions again."""
    yield
    n = _mappings()
    if n is None or n > MAX_MAPPINGS:
        jax.clear_caches()


@pytest.fixture
def compilations():
    """A context manager that lists the programs JAX compiles while it is open."""
    import contextlib
    import logging

    @contextlib.contextmanager
    def listen():
        compiled = []

        class Count(logging.Handler):
            def emit(self, record):
                if record.getMessage().startswith("Compiling "):
                    compiled.append(record.getMessage()[:120])

        handler, logger = Count(), logging.getLogger("jax")
        logger.addHandler(handler)
        try:
            with jax.log_compiles(True):
                yield compiled
        finally:
            logger.removeHandler(handler)

    return listen


# --------------------------------------------------------------------------- written files against their schemas

# a JSON file under the session's temporary folders (tmp_path, tmp_path_factory) -> (mtime_ns, size) when it was
# last checked, so that each version of a file is read once however many tests run after it was written
_checked: dict[str, tuple[int, int]] = {}


@pytest.fixture(autouse=True)
def _schema_basetemp(request, tmp_path_factory):
    """Where this test's temporary folders lie (the session's base temp), for the schema check below."""
    request.node._schema_basetemp = tmp_path_factory.getbasetemp()


def _json_files(folder: str):
    """The ``.json`` files under ``folder`` with their ``(mtime_ns, size)``."""
    stack = [folder]
    while stack:
        try:
            entries = list(os.scandir(stack.pop()))
        except OSError:
            continue
        for e in entries:
            if e.is_dir(follow_symlinks=False):
                stack.append(e.path)
            elif e.name.endswith(".json") and e.is_file(follow_symlinks=False):
                try:
                    st = e.stat()
                except OSError:
                    continue
                yield e.path, (st.st_mtime_ns, st.st_size)


def _read_back_rejects(doc: dict, path: str) -> bool:
    """Whether the project's own reader refuses the document too: a test's hand-broken input
    (a reader test), not a file the project wrote."""
    from slcvjax.observations.formats import FormatError, calibration_from_json, observations_from_json

    readers = {"slcv-observations/1": observations_from_json, "slcv-calibration/1": calibration_from_json}
    if doc.get("format") == "slcv-setup/1":
        from slcvjax.images.detect import read_setup

        readers["slcv-setup/1"] = lambda _doc, _src: read_setup(path)
    reader = readers.get(doc.get("format"))
    if reader is None:
        return False
    try:
        reader(doc, path)
    except (FormatError, ValueError):
        return True
    return False


def schema_problems(folder) -> list[str]:
    """The JSON files under ``folder`` written or changed since they were last checked that carry the
    ``format`` of a public format and do not match its schema (``slcvjax.observations.schemas``), one line each;
    files that are not JSON, of another format, or that the project's reader refuses as well are passed over."""
    import json

    from slcvjax.observations import schemas

    out = []
    for path, key in _json_files(str(folder)):
        if _checked.get(path) == key:
            continue
        _checked[path] = key
        try:
            with open(path, encoding="utf-8") as f:
                text = f.read()
            if '"format"' not in text:
                continue
            doc = json.loads(text)
        except (OSError, ValueError, RecursionError):  # a fuzzed file may nest past the parser's depth
            continue
        if not isinstance(doc, dict) or doc.get("format") not in schemas.FORMATS:
            continue
        found = schemas.errors(doc)
        if found and not _read_back_rejects(doc, path):
            where, msg = found[0]
            out.append(f"{path}: {where}: {msg[:300]}" + (f" (and {len(found) - 1} more)" if len(found) > 1 else ""))
    return out


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item):
    """After a test that passed, every JSON file of a public format written under the session's temporary folders
    since the last test (by the test or its fixtures) must match its schema: a failure names the file and field."""
    outcome = yield
    base = getattr(item, "_schema_basetemp", None)
    if outcome.excinfo is not None or base is None:
        return
    problems = schema_problems(base)
    if item.get_closest_marker("hand_written_inputs") is not None:
        return  # inputs written on purpose outside the formats (fuzzed, minimal by hand): looked at, not judged
    if problems:
        outcome.force_exception(AssertionError("written files do not match their schemas:\n" + "\n".join(problems)))
