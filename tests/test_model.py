"""The domain types `jaxsh.Lighting` / `jaxsh.TorranceSparrow` and the forward functions that take them."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsh
import solvers

from .helpers import primitives, random_dirs

D1 = np.array([0.4, 0.5, 0.77]) / np.linalg.norm([0.4, 0.5, 0.77])
D2 = np.array([-0.5, 0.2, 0.84]) / np.linalg.norm([-0.5, 0.2, 0.84])
L1 = np.array([3.0, 2.5, 2.0])
E2 = np.array([4.0, 4.0, 3.5])
KD = np.array([0.25, 0.2, 0.15])
KS = np.array([0.6, 0.6, 0.6])
V = np.array([0.0, 0.0, 1.0])


def _pixels(rng, n=60):
    nrm = random_dirs(rng, (n,))
    nrm[:, 2] = np.abs(nrm[:, 2]) + 0.2
    return nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


def test_solvers_re_exports_the_same_types():
    assert solvers.Lighting is jaxsh.Lighting
    assert solvers.TorranceSparrow is jaxsh.TorranceSparrow


def test_positional_order_and_conversion():
    sh = np.arange(9.0)
    light = jaxsh.Lighting(sh, [[0.0, 0.0, 1.0]], [2.0])
    assert light.slow_sh.shape == (9, 1) and light.fast_energy.shape == (1, 1)  # one channel, channels last
    assert isinstance(light.fast_directions, jax.Array) and light.lmax == 2 and light.n_channels == 1
    b = jaxsh.TorranceSparrow([0.1, 0.2, 0.3], 0.5, None, 0.1)
    assert b.mu is None and b.kd.shape == (3,) and b.ks.shape == () and b.sigma.shape == ()
    assert b.n_channels == 3
    # pytrees: through jit unchanged
    out = jax.jit(lambda x: x)(b)
    np.testing.assert_array_equal(out.kd, b.kd)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(), "Lighting needs"),
        (dict(fast_directions=np.ones((2, 3))), "go together"),
        (dict(disk_directions=np.ones((1, 3)), disk_radius=np.ones(1)), "go together"),
        (dict(slow_sh=np.ones((8, 3))), "slow_sh"),
        (dict(slow_sh=np.ones((9, 3, 1))), r"`slow_sh` must have shape \(n_coeffs, C\)"),
        (dict(fast_directions=np.ones((2, 2)), fast_energy=np.ones((2, 3))), r"`fast_directions` must have shape \(J, 3\)"),
        (dict(fast_directions=np.ones((2, 3)), fast_energy=np.ones((3, 3))), r"`fast_energy` must have shape \(2, C\)"),
        (dict(disk_directions=np.ones((2, 3)), disk_radius=np.ones(3), disk_radiance=np.ones((2, 3))), r"`disk_radius` must have shape \(2,\)"),
        (dict(disk_directions=np.ones((2, 3)), disk_radius=np.ones(2), disk_radiance=np.ones((1, 3))), r"`disk_radiance` must have shape \(2, C\)"),
        (dict(slow_sh=np.ones((9, 3)), fast_directions=np.ones((1, 3)), fast_energy=np.ones((1, 2))), "`fast_energy` has 2 channels"),
    ],
)
def test_lighting_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        jaxsh.Lighting(**kwargs)


@pytest.mark.parametrize(
    "args,match",
    [
        ((np.ones(3), np.ones(2), 1.5, 0.1), "`kd` and `ks`"),
        ((np.ones(3), np.ones(3), np.ones(2), 0.1), r"`mu` must be a scalar"),
        ((np.ones(3), np.ones(3), 1.5, np.ones(3)), r"`sigma` must be a scalar"),
    ],
)
def test_torrance_sparrow_validation(args, match):
    with pytest.raises(ValueError, match=match):
        jaxsh.TorranceSparrow(*args)


@pytest.mark.slow  # ~2.5 % of the suite (compiles every form) (make test-all)
def test_new_forms_equal_the_keyword_forms(rng):
    n = _pixels(rng)
    v = _pixels(rng)
    slow = jaxsh.disk_light_sh(D1, 0.3, L1, 12)
    light = jaxsh.Lighting(slow, D2[None], E2[None])
    brdf = jaxsh.TorranceSparrow(KD, KS, 1.5, 0.15)
    vis = dict(
        transfer=rng.uniform(size=(60, 9)), fast_visibility=rng.uniform(size=(60, 1)),
        reflected_visibility=rng.uniform(size=60),
    )
    for kw in ({}, vis, dict(exact_fast_diffuse=False)):
        new = jaxsh.render_practical(n, v, brdf, light, **kw)
        old = jaxsh.render_practical(n, v, KD, KS, mu=1.5, sigma=0.15, slow_sh=slow, fast_directions=D2[None], fast_energy=E2[None], **kw)
        for a, b in zip(new, old):
            np.testing.assert_array_equal(a, b)
        # the factored model is the same kernel: equal to rounding, per component
        terms = jaxsh.practical_terms(n, v, light, **kw)
        for a, b in zip(terms.components(brdf), new):
            np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-14)
        np.testing.assert_allclose(terms(brdf), new.total, rtol=1e-13, atol=1e-14)
        np.testing.assert_allclose(terms(KD, KS, 1.5, 0.15), new.total, rtol=1e-13, atol=1e-14)
    np.testing.assert_array_equal(solvers.predict(brdf, light, n, v), jaxsh.render_practical(n, v, brdf, light).total)
    # the reference renderer: disks and fast sources in the Lighting
    ref_light = jaxsh.Lighting(None, D2[None], E2[None], D1[None], [0.3], L1[None])
    a = jaxsh.render_reference(n[:10], v[:10], brdf, ref_light, disk_nodes=(8, 16))
    b = jaxsh.render_reference(n[:10], v[:10], KD, KS, 1.5, 0.15, disks=(D1[None], np.array([0.3]), L1[None]), directional=(D2[None], E2[None]), disk_nodes=(8, 16))
    np.testing.assert_array_equal(a, b)
    env = rng.uniform(size=(8, 16, 3))
    np.testing.assert_array_equal(
        jaxsh.render_reference(n[:5], v[:5], brdf, envmap=env), jaxsh.render_reference(n[:5], v[:5], KD, KS, 1.5, 0.15, envmap=env)
    )


def test_disks_split_and_total_sh():
    light = jaxsh.Lighting(
        np.ones((4, 3)), D1[None], E2[None], np.stack([D1, D2]), np.array([0.3, 0.005]), np.stack([L1, np.full(3, 1e4)])
    )
    # total_sh: each part by its own closed form
    want = np.zeros((16, 3))
    want[:4] = 1.0
    want += np.asarray(jaxsh.directional_light_sh(D1[None], E2[None], 3))
    want += np.asarray(jaxsh.disk_light_sh(D1, 0.3, L1, 3)) + np.asarray(jaxsh.disk_light_sh(D2, 0.005, np.full(3, 1e4), 3))
    np.testing.assert_allclose(light.total_sh(3), want, rtol=1e-13, atol=1e-13)
    with pytest.raises(ValueError, match="split_disks"):
        jaxsh.render_practical(np.array([[0.0, 0, 1]]), V, jaxsh.TorranceSparrow(KD, KS, 1.5, 0.1), light)
    split = light.split_disks(sigma=0.1, lmax=6)
    assert split.disk_directions is None and split.slow_sh.shape == (49, 3)
    slow, fd, fe = jaxsh.split_disk_sources(np.stack([D1, D2]), np.array([0.3, 0.005]), np.stack([L1, np.full(3, 1e4)]), 0.1, 6)
    want_slow = np.asarray(slow).copy()
    want_slow[:4] += 1.0
    np.testing.assert_allclose(split.slow_sh, want_slow, atol=1e-13)
    np.testing.assert_allclose(split.fast_directions, np.concatenate([fd, D1[None]]), atol=1e-15)
    np.testing.assert_allclose(split.fast_energy, np.concatenate([fe, E2[None]]), rtol=1e-14)
    with pytest.raises(ValueError, match="slow_sh"):
        jaxsh.render_reference(np.array([[0.0, 0, 1]]), V, jaxsh.TorranceSparrow(KD, KS, 1.5, 0.1), light)


def test_mixed_forms_are_errors():
    brdf = jaxsh.TorranceSparrow(KD, KS, 1.5, 0.1)
    light = jaxsh.Lighting(None, D2[None], E2[None])
    n = np.array([[0.0, 0.0, 1.0]])
    with pytest.raises(TypeError, match="Lighting"):
        jaxsh.render_practical(n, V, brdf, slow_sh=np.ones((9, 3)))
    with pytest.raises(TypeError, match="sigma"):
        jaxsh.render_practical(n, V, KD, KS, 1.5, fast_directions=D2[None], fast_energy=E2[None])
    with pytest.raises(TypeError, match="both"):
        jaxsh.practical_terms(n, V[None], light, slow_sh=np.ones((9, 3)))
    with pytest.raises(ValueError, match="lighting"):
        jaxsh.render_practical(n, V, brdf)
    with pytest.raises(ValueError, match="`lighting` must be a jaxsh.Lighting"):
        jaxsh.render_practical(n, V, brdf, np.ones((9, 3)))


def test_grad_through_the_types(rng):
    """`jax.grad` with respect to a TorranceSparrow / Lighting pytree, against central differences."""
    n = _pixels(rng, 20)
    light = jaxsh.Lighting(jaxsh.disk_light_sh(D1, 0.3, L1, 10), D2[None], E2[None])
    brdf = jaxsh.TorranceSparrow(KD, KS, 1.5, 0.15)

    def f(b, l):
        return jnp.sum(jaxsh.render_practical(n, V, b, l).total)

    gb, gl = jax.grad(f, argnums=(0, 1))(brdf, light)
    assert isinstance(gb, jaxsh.TorranceSparrow) and isinstance(gl, jaxsh.Lighting)
    h = 1e-6
    fd_sigma = (f(jaxsh.TorranceSparrow(KD, KS, 1.5, 0.15 + h), light) - f(jaxsh.TorranceSparrow(KD, KS, 1.5, 0.15 - h), light)) / (2 * h)
    assert float(gb.sigma) == pytest.approx(float(fd_sigma), rel=1e-6)
    e = lambda s: f(brdf, jaxsh.Lighting(light.slow_sh, D2[None], E2[None] * s))
    assert float(jnp.sum(gl.fast_energy * E2[None])) == pytest.approx(float((e(1 + h) - e(1 - h)) / (2 * h)), rel=1e-6)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_practical_terms_unchecked_evaluation(rng, dtype):
    """`check=False` (what `solvers.fit_brdf` uses inside its loops): the same values, bit for bit, and no
    run-time check in the program; with the default `check=True` a traced sigma <= 0 or mu <= 0 is an error."""
    n, v = _pixels(rng).astype(dtype), _pixels(rng).astype(dtype)
    light = jaxsh.Lighting(jaxsh.disk_light_sh(D1, 0.3, L1, 12).astype(dtype), D2[None].astype(dtype), E2[None].astype(dtype))
    terms = jaxsh.practical_terms(n, v, light)
    for mu, sigma in ((1.5, 0.15), (None, 0.05), (1.001, 0.9)):
        np.testing.assert_array_equal(terms.specular_unit(mu, sigma, check=False), terms.specular_unit(mu, sigma))
        np.testing.assert_array_equal(terms.fresnel(mu, check=False), terms.fresnel(mu))
        for a, b in zip(terms.components(KD, KS, mu, sigma, check=False), terms.components(KD, KS, mu, sigma)):
            np.testing.assert_array_equal(a, b)
            assert a.dtype == dtype
    spec = jax.jit(lambda t, m, s: t.specular_unit(m, s))
    for mu, sigma, name in ((1.5, -0.2, "sigma"), (1.5, 0.0, "sigma"), (1.5, np.inf, "sigma"), (-1.0, 0.2, "mu")):
        with pytest.raises(Exception, match=name):
            jax.block_until_ready(spec(terms, jnp.asarray(mu, dtype), jnp.asarray(sigma, dtype)))
    # the checks are what `check=False` leaves out of the program: a conditional around a host callback
    checked = primitives(jax.make_jaxpr(lambda m, s: terms.specular_unit(m, s))(1.5, 0.2).jaxpr)
    unchecked = primitives(jax.make_jaxpr(lambda m, s: terms.specular_unit(m, s, check=False))(1.5, 0.2).jaxpr)
    assert "cond" in checked and "cond" not in unchecked and "pure_callback" not in unchecked


@pytest.mark.parametrize("sigma", [-0.2, 0.0, np.inf])
def test_render_practical_traced_sigma_is_checked(rng, sigma):
    """`render_practical` evaluates its terms unchecked (`_combine`): a traced sigma out of range must still be an
    error, from its own check before the program."""
    n, v = _pixels(rng, 8), _pixels(rng, 8)
    light = jaxsh.Lighting(jaxsh.disk_light_sh(D1, 0.3, L1, 6), D2[None], E2[None])
    f = jax.jit(lambda s: jaxsh.render_practical(n, v, jaxsh.TorranceSparrow(KD, KS, 1.5, s), light).total)
    with pytest.raises(Exception, match="sigma"):
        jax.block_until_ready(f(jnp.asarray(sigma)))
    assert np.all(np.isfinite(f(jnp.asarray(0.2))))
