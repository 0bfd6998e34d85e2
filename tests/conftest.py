import os
from pathlib import Path

# one persistent compilation cache for the test processes (two xdist workers, the notebooks'
# kernels), apart from the user's: a computation compiled in one is loaded by the others
os.environ.setdefault("SLCVJAX_CACHE_DIR", str(Path(__file__).parent.parent / ".pytest_cache" / "jax"))

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import slcvjax  # noqa: F401  (enables float64)

jax.config.update("jax_numpy_dtype_promotion", "strict")


def pytest_configure(config):
    from hypothesis import settings

    settings.register_profile("slcv", deadline=None, max_examples=40, derandomize=True)
    settings.load_profile("slcv")


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """After each test file, drop the process's compiled programs (they stay in the persistent
    cache): a worker that runs many files otherwise keeps thousands of executables mapped."""
    yield
    jax.clear_caches()
