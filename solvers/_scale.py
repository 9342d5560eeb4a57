"""Scale-out with JAX's own SPMD machinery: pixel-sharded fits of one capture, batched fits of many.

Nothing here is a scheduler: the work is placed with `jax.sharding`
(`Mesh`, `NamedSharding`) and XLA's SPMD partitioner (GSPMD) splits the
existing jitted solvers and inserts the collectives.

**One large capture: shard the pixels.** Every solver's heavy work is a sum
over pixels — the normal-equation (Gram) blocks of R&H eq. 25 in
`inverse_lighting` and `factorize`, the inner $(K_d, K_s)$ systems and the
residual sums of `fit_brdf` (eq. 24):

$$A^TWA = \\sum_{d}\\ \\sum_{x \\in \\text{shard}_d} w_x\\,a_x a_x^T .$$

`shard_observations(obs, mesh)` pads `Observations` to a multiple of the mesh
size with weight-0 samples and places the per-pixel arrays along the mesh
axis with a `NamedSharding`. The solvers are then called unchanged: their
jitted programs see sharded inputs. The sums are formed in loops over chunks
of pixels (`lax.scan`), which XLA's partitioner does not split (it gathers
their inputs and runs the loops on every device), so `fit_brdf` and
`inverse_lighting` run theirs inside `jax.shard_map` on each device's pixels
and add the sums with one `psum` (`solvers._pixel_sums`); so do `factorize`'s
passes over all pixels, whose per-pixel rows stay on their devices, while its
searches run on a gathered subset of at most `search_pixels` samples
(docs/howto_scale.md, "Run-time checks and per-pixel loops on several
devices"). The solvers count observations as the samples of positive
weight (`n_obs`, RMS, standard errors), so the padding changes the
direct solves only by rounding (`inverse_lighting`: tested to 1e-10 relative
in float64, `tests/test_scale.py`) and the iterative fits within their
stopping tolerances (the rounding of the regrouped sums moves the iterates;
docs/howto_scale.md).

**Many captures: shard the batch.** `fit_many` pads every capture to a
bucket size (a power of two) with weight-0 samples, stacks the captures of a
bucket and runs the `fit_brdf` program over them (one compiled program per
bucket size and number of captures in the bucket — with a mesh, captures per
device): `vmap`ped on one device; with a `mesh`, the batch axis is sharded
(`NamedSharding`, GSPMD) — on CPU devices as a `(devices, members)` stack,
`vmap`ped over the device axis and one member at a time (`lax.map`) within a
device's block (the CPU LAPACK kernels of a batched fit deadlock with forced
host devices, see `fit_many`). Each
capture keeps its own status: a degenerate member (black images, zero
weights, no samples) reports `no_signal` and does not change the others.

**Several processes or hosts.** The same code runs under
`jax.distributed.initialize(...)`: `jax.devices()` then lists every
process's devices, `pixel_mesh()` spans them all, and every process calls the
solver with the same (full) observations — `shard_observations` builds the
global arrays with `jax.make_array_from_callback`, each process filling only
its own shards (docs/howto_scale.md). `fit_many` with a mesh over every
process's devices gathers the batch's results into every process.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

import jaxsh

from ._brdf import BRDFResult, _fit_brdf
from ._data import Lighting, Observations, practical_terms_for, view_lightings
from ._results import check_bool, check_float, check_int
from ._threads import blas_single_thread

_PIXEL_FIELDS = ("normals", "views", "values", "weights", "transfer", "fast_visibility", "reflected_visibility", "texel",
                 "view_index", "pixel_index")


def pixel_mesh(devices: Sequence | int | None = None, axis: str = "pixels") -> Mesh:
    """A one-axis `jax.sharding.Mesh` named `axis` over `devices`.

    `devices`: a list of devices, a count (the first `n` of `jax.devices()`),
    or None (all devices of all processes, `jax.devices()`).
    """
    if devices is None:
        devs = jax.devices()
    elif isinstance(devices, (bool, np.bool_, str, bytes, float, np.floating)):
        raise ValueError(f"`devices` must be a list of devices, a count or None, got {devices!r}")
    elif isinstance(devices, (int, np.integer)):
        avail = jax.devices()
        if not 1 <= devices <= len(avail):
            raise ValueError(f"`devices` must be between 1 and {len(avail)} (the devices JAX sees), got {devices}")
        devs = avail[: int(devices)]
    else:
        devs = list(devices)
        if not devs:
            raise ValueError("`devices` is empty: give at least one device")
        bad = [d for d in devs if not isinstance(d, jax.Device)]
        if bad:
            raise ValueError(f"`devices` must hold jax devices (e.g. from jax.devices()), got {bad[0]!r}")
        if len(set(devs)) != len(devs):  # a mesh over one device twice: sharding failed later with a runtime error
            raise ValueError(f"`devices` lists a device more than once: {devs!r}")
    return Mesh(np.asarray(devs, dtype=object), (axis,))


def _mesh_axis(mesh: Mesh, axis: str) -> int:
    if not isinstance(mesh, Mesh):
        raise ValueError(f"`mesh` must be a jax.sharding.Mesh (see solvers.pixel_mesh), got {type(mesh).__name__}")
    if axis not in mesh.axis_names:
        raise ValueError(f"`axis` {axis!r} is not an axis of `mesh` (axes {mesh.axis_names})")
    return int(mesh.shape[axis])


def pad_observations(obs: Observations, multiple: int = 1, size: int | None = None, *, bucket: bool = False) -> Observations:
    """`obs` with weight-0 samples appended, to a multiple of `multiple` samples (or exactly `size`).

    With `bucket=True`, first to the size bucket of its $N$ samples: $N$ rounded up to three significant bits
    (less than 25 % more samples; four buckets an octave), at least 1,024. The solvers' compiled programs
    depend on the sample count, so captures whose counts share a bucket share them: a second capture's fit
    compiles nothing in the same process, and `jaxsh fit` finds its programs in the compilation cache
    (docs/performance.md, sixteenth round). `size` and `bucket` exclude each other.

    A padded sample copies the geometry of sample 0 (normal, view, visibility
    terms, texel and indices: finite values, so no NaN can enter a sum; an
    `obs` of 0 samples gets normal and view $+z$ and zero visibility terms,
    texel and indices) with zero radiance and zero weight: it adds nothing to any weighted sum, and
    the solvers count only samples of positive weight. The results equal the
    unpadded ones to rounding (the sums are grouped differently). Outside jit;
    concrete single-device arrays (CPU or GPU) are padded on the host, each
    put back on its own device if it was committed there (an eager JAX
    concatenation would compile a program for each new count).
    Note that `to_images` of a padded `Observations` would also write the
    padded samples (onto sample 0's pixel): scatter `values[:obs.n_samples]`
    with the unpadded `obs`.
    """
    if not isinstance(obs, Observations):
        raise ValueError(f"`obs` must be an Observations (see solvers.observations), got {type(obs).__name__}")
    multiple = check_int(multiple, "multiple")
    bucket = check_bool(bucket, "bucket")
    if bucket and size is not None:
        raise ValueError("give `size` or `bucket=True`, not both")
    n = obs.n_samples
    target = _size_bucket(n) if bucket else n
    target = -(-target // multiple) * multiple if size is None else check_int(size, "size")
    if target < n:
        raise ValueError(f"`size` must be >= the {n} samples of `obs`, got {target}")
    pad = target - n
    if pad == 0:
        return obs
    arrays = [getattr(obs, f) for f in _PIXEL_FIELDS]
    host = all(a is None or isinstance(a, np.ndarray) or _one_device(a) is not None for a in arrays)

    def grow(name, a):
        if a is None:
            return None
        if host:
            # back where it was: on its device if committed there, else uncommitted (the default device)
            dev = _one_device(a) if isinstance(a, jax.Array) and a.committed else None
            a = np.asarray(a)
            if name in ("values", "weights"):
                extra = np.zeros((pad,) + a.shape[1:], a.dtype)
            elif n == 0:  # no sample 0 to copy: normal and view +z, zeros elsewhere
                extra = np.zeros((pad,) + a.shape[1:], a.dtype)
                if name in ("normals", "views"):
                    extra[:, 2] = 1
            else:
                extra = np.repeat(a[:1], pad, 0)
            return jax.device_put(np.concatenate([a, extra]), dev)  # a new array: `device_put` may alias it (CPU)
        if name in ("values", "weights"):
            extra = jnp.zeros((pad,) + a.shape[1:], a.dtype)
        elif n == 0:
            extra = jnp.zeros((pad,) + a.shape[1:], a.dtype)
            if name in ("normals", "views"):
                extra = extra.at[:, 2].set(1)
        else:
            extra = jnp.broadcast_to(a[:1], (pad,) + a.shape[1:])
        return jnp.concatenate([jnp.asarray(a), extra])

    return Observations(*(grow(f, a) for f, a in zip(_PIXEL_FIELDS, arrays)), obs.image_shapes, obs.n_texels)


def _one_device(a):
    """The device of a concrete array on one device, any platform (padded on the host); None for a tracer or a
    sharded array (padded by JAX). On a GPU too: the copy to the host and back takes milliseconds, where the
    eager `jnp` padding compiles about nine small programs for each new sample count (0.16 s each on an H200,
    docs/performance.md, "Seventeenth round")."""
    if isinstance(a, jax.core.Tracer) or not isinstance(a, jax.Array) or not a.is_fully_addressable:
        return None
    devices = a.devices()
    return next(iter(devices)) if len(devices) == 1 else None


_MIN_BUCKET = 1024


def _size_bucket(n: int) -> int:
    """The size bucket of `n` samples (`pad_observations(..., bucket=True)`): `n` rounded up to three significant
    bits, at least `_MIN_BUCKET`. For $2^{k-1} < n \\le 2^k$ the buckets are the multiples of $2^{k-3}$, so a
    bucket holds fewer than $1.25\\,n$ rows. (`jaxsh.render_practical` buckets its pixels by the same rule.)"""
    if n <= _MIN_BUCKET:
        return _MIN_BUCKET
    step = 1 << max(0, (n - 1).bit_length() - 3)
    return -(-n // step) * step


def _global_array(a, sharding: NamedSharding):
    """A global `jax.Array` with `sharding` from a host array every process holds in full."""
    a = np.asarray(a)
    return jax.make_array_from_callback(a.shape, sharding, lambda idx: a[idx])


def shard_observations(obs: Observations, mesh: Mesh, axis: str = "pixels") -> Observations:
    """Pad `obs` to a multiple of the mesh size and shard its samples over `mesh` along `axis`.

    The per-pixel arrays (`normals`, `views`, `values`, `weights`,
    visibility terms, `texel`, `view_index`, `pixel_index`) get
    `NamedSharding(mesh, PartitionSpec(axis))`: device $d$ holds samples
    $[dN/D, (d+1)N/D)$. Call `fit_brdf`, `inverse_lighting` or `factorize`
    on the result as on `obs`: the same answer to rounding, the pixel sums
    of `fit_brdf` and `inverse_lighting` computed where the pixels live
    (`factorize`'s not yet: module docstring). Padding: see
    `pad_observations`. Under `jax.distributed`, every process passes the
    same full `obs` and a mesh over the global devices.
    """
    size = _mesh_axis(mesh, axis)
    padded = pad_observations(obs, size)
    sh = NamedSharding(mesh, PartitionSpec(axis))
    arrays = {f: (None if getattr(padded, f) is None else _global_array(getattr(padded, f), sh)) for f in _PIXEL_FIELDS}
    return Observations(**arrays, image_shapes=obs.image_shapes, n_texels=obs.n_texels)


# --------------------------------------------------------------------------- many captures


def _bucket(n: int, min_bucket: int) -> int:
    # `fit_many`'s buckets are powers of two, coarser than `_size_bucket`'s: the captures of one bucket are stacked
    # and vmapped together, so fewer buckets mean fewer, larger batches
    return max(min_bucket, 1 << max(0, math.ceil(math.log2(max(n, 1)))))


def _u_grid(fresnel: bool, dt):
    # the starting grid of `fit_brdf` (init=None)
    sig_grid = np.exp(np.linspace(np.log(0.02), np.log(0.6), 12))
    mu_grid = np.array([1.2, 1.5, 2.2]) if fresnel else np.array([1.5])
    mg, sg = np.meshgrid(mu_grid, sig_grid, indexing="ij")
    return jnp.asarray(np.stack([np.log(mg.ravel() - 1), np.log(sg.ravel())], 1) if fresnel else np.log(sg.ravel())[:, None], dt)


def _fit_one(args, u_grid, fresnel, refine, max_steps, rtol, atol):
    t, b, w = args
    return _fit_brdf(t, b, w, None, u_grid, 0, fresnel, None, refine, max_steps, rtol, atol)


@jaxsh.jit
def _fit_batch(terms, b, w, u_grid, fresnel, refine, max_steps, rtol, atol, blocks):
    """The fits of a stack of captures: `vmap`ped (`blocks` False), or, with `(D, m, ...)` inputs sharded over
    `D` devices (`blocks` True), `vmap`ped over the device axis and one member at a time (`lax.map`) within a block.

    In the second form every LAPACK call (the covariance `eigh`, the Levenberg-Marquardt SVD) has batch `D` and,
    once GSPMD splits the device axis, batch 1 on each device: jaxlib's CPU kernels never fan a batch out into the
    intra-op pool that the forced host devices share (`fit_many`)."""
    def one(args):
        return _fit_one(args, u_grid, fresnel, refine, max_steps, rtol, atol)

    if not blocks:
        return jax.vmap(lambda *a: one(a))(terms, b, w)
    return jax.vmap(lambda *a: jax.lax.map(one, a))(terms, b, w)


@blas_single_thread
def fit_many(
    captures: Sequence[tuple[Observations, Lighting | Sequence[Lighting]]],
    *,
    fresnel: bool = True,
    refine: bool | None = None,
    max_steps: int = 400,
    rtol: float | None = None,
    atol: float | None = None,
    mesh: Mesh | None = None,
    axis: str | None = None,
    min_bucket: int = 256,
) -> list[BRDFResult]:
    """`fit_brdf` (R&H sec. 6.1, eq. 24) of many captures at once, one `BRDFResult` per capture.

    **Arguments:**

    - `captures`: a sequence of `(obs, lighting)` pairs, as `fit_brdf` takes
      them (homogeneous BRDF; `lighting` one `Lighting` or one per view).
      The captures may differ in size (0 samples too: `no_signal`); an
      empty sequence is a `ValueError`.
    - `fresnel`, `refine`, `max_steps`, `rtol`, `atol`: as `fit_brdf`. The
      grid and the simplex always use every sample here, so `refine=None`
      (default) runs no Levenberg–Marquardt refinement, as `fit_brdf` with
      every sample in its search.
    - `mesh`: a `jax.sharding.Mesh` (e.g. `pixel_mesh(axis="batch")`): the
      captures of a bucket are sharded over its axis `axis` (default: its
      first axis; an `axis` without a `mesh` is a `ValueError`); None: one
      device. Under `jax.distributed` the mesh may span every process's
      devices: every process passes the same captures and gets every result.
    - `min_bucket`: the smallest bucket size.

    Each capture is padded with weight-0 samples to a bucket size (the next
    power of two, at least `min_bucket`); captures with the same bucket and
    the same lighting structure (`lmax`, fast sources, channels) are stacked
    and fitted by one program, `vmap`ped without a mesh. The program depends on
    the bucket size and on the number of captures stacked (with a mesh: per
    device): a later call with the same counts compiles nothing, one with
    another number of captures in a bucket compiles it anew (measured: 3.5 s
    for 256-sample buckets on the 2-core development machine). With a mesh the stack is padded with weight-0 copies to a multiple
    of the mesh size (their results are dropped) and sharded along the batch
    axis; each device fits its block `vmap`ped on a GPU and one capture at a
    time (`lax.map`) on CPU devices. The reason:
    jaxlib runs a batched CPU LAPACK call by fanning out into the intra-op
    thread pool and waiting inside it, and forced host devices
    (`--xla_force_host_platform_device_count`) share that one pool: with 4
    devices on 2 cores a batched `eigh` hung (native stacks in
    `jax::ParallelBatchMap`), and a `vmap` over the sharded batch did not
    finish within 600 s. On a CPU the fit's own LAPACK calls (the covariance
    `eigh`, the Levenberg–Marquardt QRs) also run one member at a time
    under the `vmap` (`solvers._lapack.unbatched`): a batched call deadlocks
    with one device too, when two run at once. Every capture gets its own status (a degenerate
    one `no_signal` or `ill_conditioned`, a capture of 0 samples
    `no_signal`); the others are unaffected: each member stops at its own
    tolerance. The results equal `fit_brdf`'s (with every sample in its
    search) to rounding where the simplex takes the same steps; the padding
    reorders the sums, and where that rounding moves an iterate across the
    stopping test (a step more or less) they agree to the stopping tolerances
    (measured: 1e-15 in float64; in float32 σ to 2e-6, the covariance to
    1e-4 relative).
    """
    captures = list(captures)
    if not captures:
        raise ValueError("`captures` is empty: give at least one (obs, lighting) pair")
    fresnel = check_bool(fresnel, "fresnel")
    max_steps = check_int(max_steps, "max_steps")
    min_bucket = check_int(min_bucket, "min_bucket")
    refine = bool(check_bool(refine, "refine", none=True))  # None: as fit_brdf whose search saw every sample (no refinement)
    rtol = None if rtol is None else check_float(rtol, "rtol")
    atol = None if atol is None else check_float(atol, "atol")
    if mesh is not None:
        if not isinstance(mesh, Mesh):
            raise ValueError(f"`mesh` must be a jax.sharding.Mesh (see solvers.pixel_mesh) or None, "
                             f"got {type(mesh).__name__}")
        axis = mesh.axis_names[0] if axis is None else axis
        n_dev = _mesh_axis(mesh, axis)
    elif axis is not None:
        raise ValueError(f"`axis` ({axis!r}) needs a `mesh`: give both, or neither (one device)")
    # forced host devices share one intra-op pool, and jaxlib's batched CPU LAPACK kernels wait on that pool
    # from inside it (a deadlock, measured): on a CPU mesh each device fits its members one at a time
    batched = mesh is None or mesh.devices.flat[0].platform != "cpu"
    groups: dict = {}
    for i, cap in enumerate(captures):
        if not (isinstance(cap, (tuple, list)) and len(cap) == 2):
            raise ValueError(f"`captures[{i}]` must be a pair (obs, lighting), got {type(cap).__name__}")
        obs, lighting = cap
        if not isinstance(obs, Observations):
            raise ValueError(f"`captures[{i}][0]` must be an Observations, got {type(obs).__name__}")
        lights = view_lightings(obs, lighting, f"captures[{i}][1]")
        for lit in [lighting] if lights is None else lights:
            if lit.n_channels not in (1, obs.n_channels):
                raise ValueError(f"`captures[{i}][1]` has {lit.n_channels} channels, its images {obs.n_channels}")
        padded = pad_observations(obs, size=_bucket(obs.n_samples, min_bucket))
        terms = practical_terms_for(padded, lighting)
        leaves, tdef = jax.tree_util.tree_flatten(terms)
        key = (padded.n_samples, obs.values.shape[1], str(obs.values.dtype), tdef,
               tuple((x.shape, str(x.dtype)) for x in leaves))
        groups.setdefault(key, []).append((i, terms, padded.values, padded.weights, obs.n_samples))
    out: list = [None] * len(captures)
    for key, members in groups.items():
        dt = members[0][2].dtype
        f64 = dt == jnp.float64
        rt = (1e-8 if f64 else 1e-5) if rtol is None else float(rtol)
        at = (1e-8 if f64 else 1e-5) if atol is None else float(atol)
        stack = [(m[1], m[2], m[3]) for m in members]
        if mesh is not None and len(stack) % n_dev:
            t0, b0, w0 = stack[0]
            stack += [(t0, b0, jnp.zeros_like(w0))] * (n_dev - len(stack) % n_dev)
        terms, b, w = jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *stack)
        blocks = mesh is not None and not batched
        if mesh is not None:
            if blocks:  # (B, ...) -> (D, B / D, ...): device d fits members [d B/D, (d+1) B/D)
                terms, b, w = jax.tree_util.tree_map(lambda a: a.reshape((n_dev, -1) + a.shape[1:]), (terms, b, w))
            sh = NamedSharding(mesh, PartitionSpec(axis))
            terms, b, w = jax.tree_util.tree_map(lambda a: _global_array(a, sh), (terms, b, w))
        res = _fit_batch(terms, b, w, _u_grid(fresnel, dt), fresnel, refine, int(max_steps), rt, at, blocks)
        # one transfer, then one result per capture; a batch sharded over several processes (`jax.distributed`)
        # is gathered into every process first (device_get cannot fetch another process's shards)
        if all(a.is_fully_addressable for a in jax.tree_util.tree_leaves(res)):
            host = jax.device_get(res)
        else:
            from jax.experimental import multihost_utils

            host = multihost_utils.process_allgather(res, tiled=True)
        if blocks:
            host = jax.tree_util.tree_map(lambda a: a.reshape((-1,) + a.shape[2:]), host)
        for k, (i, *_rest, n) in enumerate(members):
            r = jax.tree_util.tree_map(lambda a, k=k: jnp.asarray(a[k]), host)
            out[i] = eqx.tree_at(lambda r: r.fitted, r, r.fitted[:n])  # the capture's own samples, not the bucket's
    return out
