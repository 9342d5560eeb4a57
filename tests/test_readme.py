"""The README's Usage examples run as written (issue 10).

The ```python block(s) of README.md's "## Usage" section are parsed from the
Markdown at test time and executed verbatim, statement by statement, after a
small prelude that defines the inputs the README leaves to the reader
(`dirs`, `values`, `gbuffers`, `images`, ... and a `grace.hdr` file in a
temporary working directory). Statements are compiled with README.md as
their file name and their README line numbers, so a failure's traceback
points at the README line.

The block is cut at its "# Reflectance sharing" comment: the lines before it
run in a module fixture (checked by the first test); the reflectance-sharing
lines (a greedy SBRDF fit with the README's `n_centers=2000`, about 20 s)
continue from its namespace in the second test, after a second prelude
that defines their inputs. The README uses the name `images` for
both parts (the views of `solvers.observations`, then the images under
directional lights of `solvers.reflectance_samples`); the second prelude
rebinds it.
"""

import ast
import os
import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsh
import jaxsh.io
import solvers
from solvers import synthetic

# Runs the README Usage block at its own sizes (factorize at lmax 12): a few minutes; `make test-all` runs it.
pytestmark = pytest.mark.slow

README = Path(__file__).resolve().parents[1] / "README.md"
SHARING_MARK = "# Reflectance sharing"


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def usage_blocks():
    """`[(first README line number, code)]` of the ```python blocks in the "## Usage" section."""
    lines = README.read_text(encoding="utf-8").splitlines()
    start = next((i for i, s in enumerate(lines) if s.strip() == "## Usage"), None)
    assert start is not None, "README.md has no '## Usage' section"
    blocks, i = [], start + 1
    while i < len(lines) and not lines[i].startswith("## "):
        if lines[i].strip() == "```python":
            j = i + 1
            while lines[j].strip() != "```":
                j += 1
            blocks.append((i + 2, "\n".join(lines[i + 1 : j])))  # 1-based number of the block's first line
            i = j
        i += 1
    assert blocks, "README.md's '## Usage' section has no ```python block"
    return blocks


def usage_statements():
    """Top-level statements of the Usage code, split at the reflectance-sharing comment: `(before, after)`.

    Each item is `(statement node, README line number)`; the nodes carry their README line numbers.
    """
    before, after = [], []
    for first, code in usage_blocks():
        # parse with the README's line numbers, so tracebacks and messages name README lines
        tree = ast.parse("\n" * (first - 1) + code, filename=str(README))
        src = code.splitlines()
        mark = next((first + k for k, s in enumerate(src) if s.strip().startswith(SHARING_MARK)), None)
        for node in tree.body:
            (after if mark is not None and node.lineno > mark or after else before).append(node)
    assert after, f"README.md's Usage block has no {SHARING_MARK!r} part"
    return before, after


def run_statements(nodes, ns, history):
    """Execute `nodes` in `ns`; append each bound top-level name's value (and each expression's value) to `history`.

    Under JAX's default promotion rules (a README reader's session), not the suite's strict ones (tests/conftest.py).
    """
    with jax.numpy_dtype_promotion("standard"), jax.numpy_rank_promotion("allow"):
        _run(nodes, ns, history)


def _run(nodes, ns, history):
    for node in nodes:
        if isinstance(node, ast.Expr):
            value = eval(compile(ast.Expression(node.value), str(README), "eval"), ns)
            history.setdefault("expressions", []).append((ast.unparse(node.value), value))
            continue
        exec(compile(ast.Module([node], type_ignores=[]), str(README), "exec"), ns)
        targets = node.targets if isinstance(node, ast.Assign) else []
        for sub in (s for t in targets for s in ast.walk(t)):
            if isinstance(sub, ast.Name) and isinstance(sub.ctx, ast.Store):
                history.setdefault(sub.id, []).append(ns[sub.id])


# --------------------------------------------------------------------------- the preludes


def prelude(workdir):
    """The inputs the README's lines before "Reflectance sharing" use but do not define."""
    rng = np.random.default_rng(0)
    # a small HDR lat-long map with +y up (as most light probes): lmax=16 needs H > 32
    sky = np.asarray(synthetic.procedural_sky(40, 80))
    jaxsh.io.write_image(os.path.join(workdir, "grace.hdr"), sky)

    n_pts = 64
    dirs = jnp.asarray(_unit(rng.standard_normal((n_pts, 3))))
    values = jnp.asarray(np.stack([1.0 + 0.5 * dirs[:, 2], 0.8 + 0.3 * dirs[:, 0], 0.6 + 0.2 * dirs[:, 1]], -1))
    n = jnp.asarray(_unit(rng.standard_normal((n_pts, 3)) * [0.2, 0.2, 1.0] + [0, 0, 1.0]))
    wi = jnp.asarray(_unit(np.asarray(n) + rng.standard_normal((n_pts, 3)) * 0.4))
    wo = jnp.asarray(_unit(np.asarray(n) + rng.standard_normal((n_pts, 3)) * 0.4))
    normals = jnp.asarray(_unit(rng.standard_normal((n_pts, 3))))

    # BRDF and lighting of the forward part; the capture below is rendered under that same lighting
    # (kd, ks small enough that most pixels stay below the README's saturation=0.99)
    kd = jnp.asarray([0.15, 0.12, 0.09])
    ks = jnp.asarray([0.05, 0.05, 0.05])
    d_area = jnp.asarray(_unit([0.45, -0.55, 0.7]))
    d_sun = jnp.asarray(_unit([-0.35, 0.5, 0.8]))
    sources = (
        (np.asarray(d_area)[None], np.array([0.3]), np.array([[3.0, 2.5, 2.0]])),
        (np.asarray(d_sun)[None], np.array([[4.0, 4.0, 3.5]])),
    )
    truth = solvers.TorranceSparrow(kd, ks, jnp.asarray(1.5), jnp.asarray(0.15))
    cap = solvers.sphere_capture(truth, size=24, n_views=3, noise=0.005, sources=sources, disk_nodes=(32, 64))
    gbuffers, images = cap.gbuffers, cap.images
    masks = [np.asarray(gb.mask) for gb in gbuffers]
    # two texels: left and right half of each view
    texels = [(np.arange(m.shape[1])[None, :] >= m.shape[1] // 2).astype(np.int32) * np.ones_like(m, np.int32)
              for m in masks]
    new_lighting = solvers.Lighting(slow_sh=jaxsh.disk_light_sh(jnp.asarray(_unit([0.0, 0.6, 0.8])), 0.4,
                                                               jnp.asarray([2.0, 2.0, 2.0]), 12))
    return dict(dirs=dirs, values=values, wi=wi, wo=wo, n=n, normals=normals, kd=kd, ks=ks, d_area=d_area,
                d_sun=d_sun, gbuffers=gbuffers, images=images, masks=masks, texels=texels, new_lighting=new_lighting)


def sharing_prelude(ns):
    """The inputs of the README's reflectance-sharing lines: images of a sphere under directional lights."""
    size, n_lights = 32, 5
    normal, mask, xy = synthetic.sphere_geometry(size)
    lights = synthetic.cone_lights(n_lights, 0.8)
    images = synthetic.render_images(synthetic.metallic_brdf, normal, mask, lights)
    return dict(images=images, normal=normal, view=synthetic.VIEW, lights=lights, mask=mask, xy=xy,
                new_light=_unit([0.3, -0.2, 0.9]), points=ns["dirs"], n_centers=20)


# --------------------------------------------------------------------------- tests


@pytest.fixture(scope="module")
def forward_and_inverse(tmp_path_factory):
    """Run the README's Usage lines before "Reflectance sharing": `(namespace, history)`."""
    workdir = tmp_path_factory.mktemp("readme")
    before, _ = usage_statements()
    ns = {"__name__": "readme_usage"}
    ns.update(prelude(str(workdir)))
    history = {}
    cwd = os.getcwd()
    os.chdir(workdir)
    try:
        run_statements(before, ns, history)
    finally:
        os.chdir(cwd)
    return ns, history


def test_readme_usage_forward_and_inverse(forward_and_inverse):
    ns, hist = forward_and_inverse
    assert ns["env"].shape == (40, 80, 3)
    assert ns["L"].shape == (289, 3)
    assert hist["img"][0].shape == (128, 256, 3)
    assert ns["Y"].shape == (64, 81)
    assert ns["c"].shape == (25, 3)
    assert ns["E"].shape == (64, 3)
    assert np.asarray(ns["A"]).shape == (17,)
    assert ns["rho"].shape == (64,)
    assert hist["B"][0].total.shape == (256, 256, 3)
    assert ns["image"].shape == (256, 256, 3)
    g = ns["g"]
    assert np.all(np.asarray(ns["image"])[~np.asarray(g.mask)] == 0.0)  # "0 off the sphere"
    # the keyword form and the domain-type form render the same image
    assert len(hist["B"]) == 2
    np.testing.assert_allclose(np.asarray(hist["B"][1].total), np.asarray(hist["B"][0].total), rtol=1e-12, atol=0)
    assert ns["ref"].shape == (256, 256, 3)
    # "fit.brdf, fit.std_errors, solvers.status_name(fit.status)"
    exprs = dict(hist["expressions"])
    brdf_fit, std, status = exprs["(fit.brdf, fit.std_errors, solvers.status_name(fit.status))"]
    assert isinstance(status, str)
    assert isinstance(brdf_fit, solvers.TorranceSparrow)
    assert solvers.status_name(ns["fit"].status) == "converged"  # throw=True returned
    assert isinstance(ns["tex"], solvers.Solution)
    assert ns["il"].estimate is not None
    kd, ks = np.asarray(ns["fac"].brdf.kd), np.asarray(ns["fac"].brdf.ks)
    np.testing.assert_allclose(kd + ks, 1.0, rtol=1e-9)  # "Kd + Ks = 1"
    assert np.all(np.asarray(exprs["fac.source.sigma"]) > 0.0)
    new = np.asarray(ns["new"])
    assert new.shape == (256, 256, 3) and np.all(np.isfinite(new))


def test_readme_usage_reflectance_sharing(forward_and_inverse):
    _, after = usage_statements()
    ns, hist = dict(forward_and_inverse[0]), {}
    ns.update(sharing_prelude(ns))
    run_statements(after, ns, hist)
    assert ns["smp"].points.shape[1] == 5
    assert int(ns["sbrdf"].fit.model.n_centers) == 2000
    assert isinstance(solvers.status_name(ns["sbrdf"].status), str)
    img = np.asarray(ns["img"])
    assert img.shape == (32, 32, 3) and np.all(np.isfinite(img))
    assert np.all(img[~ns["mask"]] == 0.0)
    assert ns["rbf"](ns["points"]).shape == (64, 3)
