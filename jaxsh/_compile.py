"""How jaxsh's programs are compiled: `jit` and the XLA options it passes (`compile_options`).

A user's first call is mostly XLA compilation (issue 13, docs/performance.md). On the CPU, XLA
compiles its elementwise fusions either with its MLIR "fusion emitters" (the default of recent
jaxlib) or with its older LLVM IR emitters. For jaxsh's programs the older emitters compile
faster and the programs run as fast: measured on a 2-core machine, interleaved runs,
`solvers.fit_brdf`'s program 3.3-3.6 s → 2.0-2.1 s of compilation (-40 %), the first
`solvers.fit_brdf` call on 3×256² 7.7-8.8 s → 5.7-5.8 s, the first `solvers.factorize` call
20-22 s → 15 s (-30 %), the first exact `render_practical` 2.6-2.8 s → 1.7-1.9 s, two test files
of the suite 242 s → 184 s (-24 %); warm times within the run-to-run noise (real_sh,
project_latlong, render_practical, fit_brdf, factorize). docs/performance.md has the table.

These are options of each compiled program (`jax.jit(..., compiler_options=...)`), not of the
process: nothing global changes, and a program the user jits is compiled as the user says.

Matrix products are traced at full precision (`_full_precision`), so float32 stays float32 on a GPU
rather than TF32; and `by_platform` picks a kernel's form for the platform a program is compiled for.

`jit(..., optimize=False)` adds XLA's backend optimization level 0 (XLA's default is 3) for a program
that runs once per call and briefly, where the compilation is most of what the user waits for:
`solvers.factorize`'s `_lighting_and_source` and `_refine_final` (and `_golden_batch` until session 29)
compiled in 1.9 s less in all (3×256², XLA's own log: 5.4 s → 3.5 s over the call's programs) and ran
60-100 ms slower per call in all (docs/performance.md, "Eleventh round"). `_golden_batch` runs once per
round of the μ search, four or more times a call: at level 0 it took 12 ms a call against 2 ms, so it is
optimized again ("Twenty-second round").
"""

from __future__ import annotations

import functools
import os
from typing import Any

import equinox as eqx
import jax
import numpy as np

# the option and the value jaxsh compiles with (see the module docstring)
_WANTED = {"xla_cpu_use_fusion_emitters": False}
# added for the programs of `jit(..., optimize=False)`
_UNOPTIMIZED = {"xla_backend_optimization_level": 0}


@functools.lru_cache(maxsize=None)
def _probed_options(optimize: bool = True) -> tuple[tuple[str, Any], ...]:
    flags = os.environ.get("XLA_FLAGS", "")
    out = []
    for name, value in (_WANTED if optimize else {**_WANTED, **_UNOPTIMIZED}).items():
        if name in flags:  # the user chose it for the process: theirs wins
            continue
        try:  # this jax/jaxlib knows the option (older ones do not have it; newer ones may drop it)
            jax.jit(lambda x: x + 1, compiler_options={name: value}).lower(np.float32(0)).compile()
        except Exception:  # noqa: BLE001 - any failure means: compile without the option
            continue
        out.append((name, value))
    return tuple(out)


def compile_options(optimize: bool = True) -> dict[str, Any]:
    """The XLA compile options of jaxsh's jitted programs (a new dict; empty when none apply).

    `{"xla_cpu_use_fusion_emitters": False}` where the installed jaxlib has the option: XLA's
    LLVM IR emitters compile jaxsh's programs 25-40 % faster than its MLIR fusion emitters and the
    programs run as fast (docs/performance.md, "First calls"). With `optimize=False` (the programs
    of `jaxsh.jit(..., optimize=False)`), also `{"xla_backend_optimization_level": 0}`: faster
    compilation, slower code (module docstring). An option is left out when `XLA_FLAGS` names it
    (the process's setting then applies) or when this jaxlib rejects it; checked once per process,
    at the first call of a jaxsh program, by compiling a one-line program. Pass the result to your
    own `jax.jit(..., compiler_options=...)` to compile a pipeline around jaxsh the same way, or use
    `jaxsh.jit`.
    """
    return dict(_probed_options(_checked_optimize(optimize)))


def _checked_optimize(optimize):
    """`optimize` itself, or a `ValueError` when it is not a bool (`compile_options`, `jit`)."""
    if not isinstance(optimize, bool):
        raise ValueError(f"`optimize` must be a bool, got {optimize!r}")
    return optimize


def by_platform(*args, cpu, other):
    """`cpu(*args)` in a program compiled for a CPU, `other(*args)` in one compiled for another platform (GPU).

    For kernels whose best form differs: a loop over cache-sized chunks on a CPU is thousands of small kernel
    launches on a GPU. `jax.lax.platform_dependent` makes the choice when the program is lowered for its
    device (arrays committed to the CPU on a GPU machine get the CPU form). In a process whose default
    backend is the CPU, no other platform can be lowered for, so only `cpu` is traced (tracing both cost a
    first `real_sh` call about 50 ms).
    """
    if jax.default_backend() == "cpu":
        return cpu(*args)
    return jax.lax.platform_dependent(*args, cpu=cpu, default=other)


def _full_precision(fun):
    """`fun` traced with `jax.default_matmul_precision("highest")` unless the user chose a precision.

    JAX's default precision lets an accelerator compute float32 matrix products in a reduced format:
    NVIDIA GPUs use TF32 (a 10-bit mantissa), so a float32 product carries relative errors near 1e-3 rather
    than 1e-7. Measured on an H200 (docs/performance.md, "Seventeenth round"): `render_reference`'s pairwise
    form in float32 off by 0.15-1.6 % against its 2e-4 bound, the float32 RBF evaluation 7x over its bound
    (3.7e-3 against 5e-4), the float32 reflectance-sharing fit 1.3x over. jaxsh's float32 accuracy is the
    same on every platform: its programs trace their products at full precision. The setting is read when a
    program is traced, so it applies inside the program only (no global flag changes), and a precision the
    user set (`jax_default_matmul_precision`, globally or in a `with` block around the call) is kept. On the
    CPU the numbers did not change (nine outputs of the solvers and kernels, bitwise) and neither did the
    first calls (interleaved A/B, within the noise).
    """

    @functools.wraps(fun)
    def traced(*args, **kwargs):
        if jax.config.jax_default_matmul_precision is not None:  # the user's choice, or an enclosing program's
            return fun(*args, **kwargs)
        with jax.default_matmul_precision("highest"):
            return fun(*args, **kwargs)

    return traced


class _LazyJit:
    """`eqx.filter_jit(fun)`, compiled with `compile_options()` when it is the outermost program.

    JAX accepts compile options on a top-level `jax.jit` only: a call made while another function
    is being traced (the caller's own `jax.jit`, or a jaxsh program calling another) is staged
    into the caller's program, which is compiled as the caller says. Both versions are built at
    the first call, so that importing jaxsh initializes no backend and compiles nothing."""

    def __init__(self, fun, kwargs, optimize=True):
        self._fun = fun
        self._kwargs = kwargs
        self._optimize = optimize
        self._plain = None
        self._tuned = None
        functools.update_wrapper(self, fun)

    def _versions(self):
        if self._plain is None:
            opts = compile_options(self._optimize)
            fun = _full_precision(self._fun)
            self._tuned = eqx.filter_jit(fun, compiler_options=opts, **self._kwargs) if opts else None
            self._plain = eqx.filter_jit(fun, **self._kwargs)
        return self._plain, self._tuned

    def __call__(self, *args, **kwargs):
        plain, tuned = self._versions()
        if tuned is None or any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves((args, kwargs))):
            return plain(*args, **kwargs)
        try:
            return tuned(*args, **kwargs)
        except ValueError as e:  # staged into a caller's trace with constant arguments only
            if "compiler_options" not in str(e):
                raise
            return plain(*args, **kwargs)

    def lower(self, *args, **kwargs):
        plain, tuned = self._versions()
        return (tuned or plain).lower(*args, **kwargs)


def jit(fun=None, *, optimize: bool = True, **kwargs):
    """`equinox.filter_jit` (arrays traced, everything else static) compiled with `compile_options()`.

    Usable as `@jaxsh.jit`, `jaxsh.jit(f)` or `jaxsh.jit(donate="all")(f)`; `kwargs` are those of
    `equinox.filter_jit`. Every jitted program of jaxsh and of `solvers` is made this way.
    `optimize=False`: compiled with `compile_options(optimize=False)` (XLA's backend optimization
    level 0), for a program whose compilation costs far more than its run (module docstring).
    Matrix products are traced at full precision unless the user set `jax_default_matmul_precision`
    (`_full_precision`: float32 means float32 on a GPU too, not TF32).
    """
    _checked_optimize(optimize)
    if fun is None:
        return functools.partial(jit, optimize=optimize, **kwargs)
    return _LazyJit(fun, kwargs, optimize)


def row_sharding(x):
    """`(mesh, axis)` when `x` is a concrete `jax.Array` whose first axis, and only it, is split over more than one
    device along one mesh axis, evenly; else None (one device, replicated, another layout, or a tracer).

    The kernels that loop over chunks of points (`real_sh` beyond degree 2) then run under `jax.shard_map` on
    each device's rows (`on_row_shards`): XLA's partitioner does not split such a loop, it gathers the loop's
    input and runs the whole loop on every device (docs/howto_scale.md)."""
    sh = getattr(x, "sharding", None)
    if isinstance(x, jax.core.Tracer) or not isinstance(sh, jax.sharding.NamedSharding) or x.ndim < 2:
        return None
    spec = tuple(sh.spec) + (None,) * (x.ndim - len(sh.spec))
    axis = spec[0]
    if not isinstance(axis, str) or any(s is not None for s in spec[1:]):
        return None
    k = sh.mesh.shape[axis]
    return (sh.mesh, axis) if k > 1 and x.shape[0] % k == 0 else None


def rows_sharding(*rows):
    """`row_sharding` of the first array of `rows` when every other array of `rows` (None skipped) is split the same
    way, else None."""
    arrays = [a for a in rows if a is not None]
    where = row_sharding(arrays[0]) if arrays else None
    if where is None or any(row_sharding(a) != where or a.shape[0] != arrays[0].shape[0] for a in arrays[1:]):
        return None
    return where


def on_row_shards(fn, where, rows: tuple, shared: tuple = (), out_axis: int = 0, replicated: tuple = ()):
    """`fn(*rows, *shared)` on each device's rows (`jax.shard_map` over `where = (mesh, axis)` of `row_sharding`):
    the arrays of `rows` (or None) split along their first axis, those of `shared` replicated. Every output leaf is
    split along its axis `out_axis`, except the fields named in `replicated` (the same on every device, e.g.
    `PracticalTerms.fast_energy`). Call inside a jitted program."""
    mesh, axis = where
    spec = jax.sharding.PartitionSpec

    def row_spec(a):
        return None if a is None else spec(axis, *(None,) * (a.ndim - 1))

    def out_spec(path, leaf):
        name = getattr(path[-1], "name", None) if path else None
        if name in replicated:
            return spec()
        parts = [None] * leaf.ndim
        parts[out_axis] = axis
        return spec(*parts)

    k = mesh.shape[axis]
    local = tuple(None if a is None else jax.ShapeDtypeStruct((a.shape[0] // k,) + a.shape[1:], a.dtype) for a in rows)
    out_specs = jax.tree_util.tree_map_with_path(out_spec, jax.eval_shape(lambda r: fn(*r, *shared), local))
    in_specs = (tuple(row_spec(a) for a in rows), tuple(None if a is None else spec() for a in shared))
    return jax.shard_map(lambda r, s: fn(*r, *s), mesh=mesh, in_specs=in_specs, out_specs=out_specs)(rows, shared)
