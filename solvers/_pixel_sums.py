"""Sums over pixels that run where the pixels are: one device, or each device's shard and an all-reduce.

The solvers form their normal equations and residual sums in loops over chunks of pixels (`lax.scan`). Given
sharded pixels (`shard_observations`), XLA's partitioner does not split such a loop: it all-gathers the
loop's inputs and runs the whole loop on every device (docs/howto_scale.md, "Run-time checks and per-pixel
loops on several devices"). `sum_over_pixels` runs the loop inside `jax.shard_map` instead, on each
device's own pixels, and adds the per-device sums with one `psum`:

$$\\sum_x f(x) = \\sum_d \\sum_{x \\in \\text{shard}_d} f(x).$$

Measured (1,968 pixels, 2 host devices): `accumulate_gram` alone (lmax 8) 7 all-gathers and 2 all-reduces by
the partitioner, none and 1 inside `shard_map`, the blocks equal to 5e-16 relative; `inverse_lighting`'s
program 10 all-gathers and 11 all-reduces, now none and 3 (14 and 11 in its literal form, now none and 3).

`map_over_pixels` does the same for a function whose outputs are per-pixel arrays (`jaxsh.practical_terms`
of `fit_brdf`): each device maps its own pixels, and the outputs stay sharded. `sum_and_columns_over_pixels`
does both in one pass (`factorize`'s pass over all pixels: the eq.-25 blocks, summed, and every pixel's rows,
left on its device).

`pixel_sharding(x)` reads the mesh and axis from a concrete array (outside `jit`); the solvers pass it to
their jitted programs as a static argument, so one device and each mesh compile their own program. Call these
functions inside a jitted program: called eagerly, the `jax.shard_map` of a new closure is compiled again at
every call (`fit_brdf`'s per-pixel terms were, 1.1 s a warm call against 0.03 s: `solvers._data._terms_on_devices`).
"""

from __future__ import annotations

import jax
from jax.sharding import Mesh, NamedSharding, PartitionSpec


def pixel_sharding(x) -> tuple[Mesh, str] | None:
    """`(mesh, axis)` when the first axis of the concrete array `x` is sharded over more than one device along
    one mesh axis (`shard_observations`), else None (one device, replicated, or a tracer)."""
    sh = getattr(x, "sharding", None)
    if not isinstance(sh, NamedSharding) or sh.mesh.size < 2 or len(sh.spec) == 0:
        return None
    axis = sh.spec[0]
    if not isinstance(axis, str) or sh.mesh.shape[axis] < 2:
        return None
    return sh.mesh, axis


def sum_over_pixels(fn, where: tuple[Mesh, str] | None, pixels: tuple, shared: tuple = ()):
    """`fn(*pixels, *shared)`, a pytree of sums over the pixels of `pixels` (arrays or None, pixels first).

    `where` None: `fn` itself. `where = (mesh, axis)`: `fn` on each device's pixels (`jax.shard_map`, the
    `pixels` split along `axis`, `shared` replicated), the results added over the devices (`psum`). Every
    output must be a sum over pixels (a count, a Gram block, a residual sum), never a per-pixel array.
    """
    if where is None:
        return fn(*pixels, *shared)
    mesh, axis = where

    def local(pix, rest):
        return jax.tree.map(lambda a: jax.lax.psum(a, axis), fn(*pix, *rest))

    spec = PartitionSpec(axis)
    # check_vma=False: the loops' carries start as constants (the same on every device) and become per-device
    # sums; the psum makes the outputs equal on every device, as out_specs P() states
    return jax.shard_map(local, mesh=mesh, in_specs=(spec, PartitionSpec()), out_specs=PartitionSpec(),
                         check_vma=False)(tuple(pixels), tuple(shared))


def sum_and_columns_over_pixels(fn, where: tuple[Mesh, str] | None, pixels: tuple, shared: tuple = ()):
    """`fn(*pixels, *shared)` returning `(sums, columns)`: a pytree of sums over the pixels (as `sum_over_pixels`)
    and a pytree of per-pixel arrays whose *last* axis is the pixels' (design rows `(k, N)`, as `factorize`'s
    all-pixel pass writes them).

    `where` None: `fn` itself. `where = (mesh, axis)`: `fn` on each device's pixels (`jax.shard_map`, the `pixels`
    split along `axis`, `shared` replicated); the sums added over the devices (`psum`), the columns left where they
    were made, sharded along `axis` on their last axis. `fn` must return columns of exactly its local pixel count
    (no padding), so that the devices' columns line up with the pixels.
    """
    if where is None:
        return fn(*pixels, *shared)
    mesh, axis = where

    def local(pix, rest):
        sums, cols = fn(*pix, *rest)
        return jax.tree.map(lambda a: jax.lax.psum(a, axis), sums), cols

    sums_shape, cols_shape = jax.eval_shape(fn, *pixels, *shared)
    out_specs = (jax.tree.map(lambda _: PartitionSpec(), sums_shape),
                 jax.tree.map(lambda a: PartitionSpec(*(None,) * (a.ndim - 1), axis), cols_shape))
    spec = PartitionSpec(axis)
    return jax.shard_map(local, mesh=mesh, in_specs=(spec, PartitionSpec()), out_specs=out_specs,
                         check_vma=False)(tuple(pixels), tuple(shared))


def map_over_pixels(fn, where: tuple[Mesh, str] | None, pixels: tuple, replicated: tuple[str, ...] = ()):
    """`fn(*pixels)`, whose outputs are per-pixel arrays (leading axis the pixels') or, for the fields named in
    `replicated`, the same on every device (e.g. `PracticalTerms.fast_energy`).

    `where` None: `fn` itself. `where = (mesh, axis)`: `fn` on each device's pixels (`jax.shard_map`); the
    per-pixel outputs stay sharded along `axis`.
    """
    if where is None:
        return fn(*pixels)
    mesh, axis = where
    n = next(a for a in pixels if a is not None).shape[0]

    def spec(path, leaf):
        name = getattr(path[-1], "name", None) if path else None
        return PartitionSpec() if name in replicated or leaf.shape[:1] != (n,) else PartitionSpec(axis)

    out_specs = jax.tree_util.tree_map_with_path(spec, jax.eval_shape(fn, *pixels))
    return jax.shard_map(lambda pix: fn(*pix), mesh=mesh, in_specs=(PartitionSpec(axis),), out_specs=out_specs,
                         check_vma=False)(tuple(pixels))
