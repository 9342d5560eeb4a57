"""Test configuration: float64, strict promotion, hypothesis profiles.

The library never flips global JAX flags; the test-suite does, here.
Hypothesis profiles: "ci" (default, fast) and "thorough"
(`HYPOTHESIS_PROFILE=thorough pytest`).
"""

import os
import warnings

import jax
import numpy as np
import pytest
from hypothesis import HealthCheck, settings

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
jax.config.update("jax_numpy_rank_promotion", "raise")

warnings.filterwarnings("ignore", category=DeprecationWarning, module="jaxopt")

settings.register_profile(
    "ci",
    max_examples=15,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
settings.register_profile(
    "thorough",
    max_examples=300,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
