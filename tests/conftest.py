"""Test configuration: float64, strict promotion, hypothesis profiles, the type-check hook.

The library never flips global JAX flags; the test-suite does, here.
Hypothesis profiles: "ci" (default, fast) and "thorough"
(`HYPOTHESIS_PROFILE=thorough pytest`).

Shapes in signatures are checked by jaxtyping's import hook with beartype
(`--jaxtyping-packages=jaxsh,solvers,tests._typecheck.typechecker` in
pyproject's `addopts`; see tests/_typecheck.py; pytest-xdist workers get it too). Inside `pytest.raises(...)` the
check is switched off (`jaxtyping.config.jaxtyping_disable`): those blocks test
the library's own errors (a `ValueError` naming the argument and the expected
shape, DESIGN.md), which is what a user gets, since the annotation check runs
only here. Everywhere else a call that breaks its annotation fails the test.

The suite's compiled programs are shared through JAX's persistent compilation cache, in a
temporary folder made for the run and removed after it (`pytest_configure`; xdist's workers
inherit it through `JAXSH_TEST_XLA_CACHE`, so the two workers share it). The caches in memory
are dropped after every module (`_free_compiled_programs`), and many modules compile the same
programs at the same shapes: on 2 cores the CI suite took 11:15 with the shared cache against
14:36 without (docs/performance.md, "Thirty-second round"). A cached program is the executable
XLA compiled for the same program and options, read back from disk. `JAXSH_TEST_XLA_CACHE=off`
runs without it; a folder named there is used and kept.
"""

import functools
import os
import shutil
import tempfile
import warnings

import jax
import jaxtyping
import numpy as np
import pytest

from . import _typecheck as _typecheck  # the hook's typechecker; before any `import jaxsh`
from hypothesis import HealthCheck, settings

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
jax.config.update("jax_numpy_rank_promotion", "raise")

warnings.filterwarnings("ignore", category=DeprecationWarning, module="jaxopt")

_XLA_CACHE = "JAXSH_TEST_XLA_CACHE"


def pytest_configure(config):
    """The run's shared compilation cache (module docstring): made by the first process (xdist's controller, or
    the only one), before xdist starts its workers, which find it in their environment."""
    folder = os.environ.get(_XLA_CACHE)
    if folder is None and not hasattr(config, "workerinput"):
        folder = tempfile.mkdtemp(prefix="jaxsh-tests-xla-")
        os.environ[_XLA_CACHE] = folder
        config._jaxsh_xla_cache_made = folder
    if folder and folder != "off":
        jax.config.update("jax_compilation_cache_dir", folder)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def pytest_unconfigure(config):
    folder = getattr(config, "_jaxsh_xla_cache_made", None)
    if folder is not None:
        shutil.rmtree(folder, ignore_errors=True)
        os.environ.pop(_XLA_CACHE, None)


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


class _Unchecked:
    """`pytest.raises(...)`'s context with jaxtyping's runtime check off inside it."""

    def __init__(self, ctx):
        self._ctx = ctx
        self._prev = None

    def __enter__(self):
        self._prev = jaxtyping.config.jaxtyping_disable
        jaxtyping.config.update("jaxtyping_disable", True)
        return self._ctx.__enter__()

    def __exit__(self, *exc):
        try:
            return self._ctx.__exit__(*exc)
        finally:
            jaxtyping.config.update("jaxtyping_disable", self._prev)

    def __getattr__(self, name):
        return getattr(self._ctx, name)


_pytest_raises = pytest.raises


@functools.wraps(_pytest_raises)
def _raises_unchecked(*args, **kwargs):
    if len(args) > 1:  # the legacy form pytest.raises(E, func, *args)
        with _Unchecked(_pytest_raises(args[0])) as info:
            args[1](*args[2:], **kwargs)
        return info
    return _Unchecked(_pytest_raises(*args, **kwargs))


pytest.raises = _raises_unchecked


@pytest.fixture(scope="module", autouse=True)
def _free_compiled_programs():
    """Drop JAX's compiled programs after each test module.

    Every XLA:CPU executable keeps a few memory mappings of JIT code (about 3
    per program). A pytest-xdist worker that runs hundreds of test modules
    compiles thousands of programs and reaches the kernel's `vm.max_map_count`
    (65530 by default); LLVM then segfaults inside `backend_compile_and_load`
    when its next `mmap` fails. Measured: a worker at 62,776 mappings after
    ~20 minutes of the suite, two such crashes in two runs. `jax.clear_caches`
    plus a collection returns the mappings (300 programs: 1388 -> 505).
    """
    yield
    import gc

    jax.clear_caches()
    gc.collect()
