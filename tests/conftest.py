import jax
import numpy as np
import pytest

import slcvjax  # noqa: F401  (enables float64)

jax.config.update("jax_numpy_dtype_promotion", "strict")


def pytest_configure(config):
    from hypothesis import settings

    settings.register_profile("slcv", deadline=None, max_examples=40, derandomize=True)
    settings.load_profile("slcv")


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
