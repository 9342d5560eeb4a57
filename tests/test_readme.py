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

Those two tests run the README's own sizes (factorize at lmax 12, 2,000 RBF centres): 53-62 s on 2 cores at
XLA's optimization level 0, a few minutes at the default. They are marked slow (`make test-all`; `make demo`
runs the end-to-end pipeline): they ran in `make test` for one session (docs/performance.md, "Thirtieth
round"), until a slower CPU took the suite to its 15-minute line ("Thirty-first round"). The fast tests below
keep `make test` watching the README: every
`jaxsh.*` / `solvers.*` name it shows exists and every call of one in the Usage block binds to the callee's
signature (the arguments' count and keywords), every repository path and link it gives exists (with the
heading an anchor names), and every `make` target it names is in the Makefile.
"""

import ast
import inspect
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

README = Path(__file__).resolve().parents[1] / "README.md"
SHARING_MARK = "# Reflectance sharing"


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def usage_blocks():
    """`[(first README line number, code)]` of the ```python blocks in the "## Usage" section."""
    text = README.read_text(encoding="utf-8")
    assert "\n## Usage\n" in text, "README.md has no '## Usage' section"
    blocks = usage_blocks_of(text)
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


# The two tests that run the README Usage block at its own sizes (factorize at lmax 12): a few minutes;
# `make test-all` runs them, `make test` the fast checks further below.
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


@pytest.mark.slow
def test_readme_usage_forward_and_inverse(forward_and_inverse):
    ns, hist = forward_and_inverse
    assert ns["env"].shape == (40, 80, 3)
    assert ns["L"].shape == (289, 3)
    assert hist["img"][0].shape == (128, 256, 3)
    assert ns["Y"].shape == (64, 81)
    # "coeffs_first=True: (81, ...)": the transpose, exactly
    assert ns["Yt"].shape == (81, 64)
    np.testing.assert_array_equal(np.asarray(ns["Yt"]), np.asarray(ns["Y"]).T)
    # "L_rot: coefficients of f(R^T w)": the rotated expansion at w equals the original one at R^T w
    # (direction rows d: the rows of d @ R are (R^T w)^T), at the prelude's random directions
    # (the README's L is float32: read_envmap returns the file's float32 and the library follows it)
    d, R = np.asarray(ns["dirs"]), np.asarray(ns["R"], np.float64)
    L, L_rot = np.asarray(ns["L"], np.float64), np.asarray(ns["L_rot"], np.float64)
    lhs, rhs = np.asarray(jaxsh.real_sh(d, 16)) @ L_rot, np.asarray(jaxsh.real_sh(d @ R, 16)) @ L
    np.testing.assert_allclose(lhs, rhs, rtol=0, atol=1e-6 * np.abs(rhs).max())
    assert ns["c"].shape == (25, 3)
    assert ns["E"].shape == (64, 3)
    assert np.asarray(ns["A"]).shape == (17,)
    # "ok, lstar = recoverable_orders(A, noise=0.01)": a mask per band and the largest l with all bands <= l usable
    ok, lstar = ns["ok"], ns["lstar"]
    assert np.asarray(ok).shape == (17,) and isinstance(lstar, int)
    assert np.all(np.asarray(ok)[: lstar + 1]) and (lstar == 16 or not np.asarray(ok)[lstar + 1])
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
    # "obs.to_images(fit.fitted): the fitted model at every sample, as images": one image per view, 0 (the default
    # fill) off the mask
    fitted = ns["obs"].to_images(ns["fit"].fitted)
    assert len(fitted) == len(ns["images"])
    for im, m in zip(fitted, ns["masks"]):
        assert np.asarray(im).shape == m.shape + (3,)
        assert np.all(np.asarray(im)[~m] == 0.0)
    # "Every result is a solvers.Solution: estimate, status, iterations, rms, rel_rms, stats"
    for name in ("fit", "tex", "il", "fac"):
        res = ns[name]
        assert isinstance(res, solvers.Solution), name
        for field in ("estimate", "status", "iterations", "rms", "rel_rms", "stats"):
            assert getattr(res, field) is not None, (name, field)
    # "il.supported_lmax, il.singular_values"
    assert np.asarray(ns["il"].supported_lmax).shape == (3,) and np.asarray(ns["il"].singular_values).size > 0
    kd, ks = np.asarray(ns["fac"].brdf.kd), np.asarray(ns["fac"].brdf.ks)
    np.testing.assert_allclose(kd + ks, 1.0, rtol=1e-9)  # "Kd + Ks = 1"
    assert np.all(np.asarray(exprs["fac.source.sigma"]) > 0.0)
    new = np.asarray(ns["new"])
    assert new.shape == (256, 256, 3) and np.all(np.isfinite(new))


@pytest.mark.slow
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


# --------------------------------------------------------------------------- fast checks (make test)

ROOTS = {"jaxsh": jaxsh, "solvers": solvers}
NAME = re.compile(r"\b(?:jaxsh|solvers)(?:\.[A-Za-z_]\w*)+")


def _dotted(node):
    """`"a.b.c"` of a `Name` / `Attribute` chain, else None."""
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name):
        return None
    return ".".join([node.id, *reversed(parts)])


def _resolve(dotted):
    """The object `dotted` (rooted at jaxsh or solvers) names; AttributeError if there is none."""
    root, *rest = dotted.split(".")
    obj = ROOTS[root]
    for part in rest:
        obj = getattr(obj, part)
    return obj


def usage_blocks_of(text):
    """`[(first line number (1-based), code)]` of the ```python blocks in the "## Usage" section of `text`."""
    lines = text.splitlines()
    start = next(i for i, s in enumerate(lines) if s.strip() == "## Usage")
    blocks, i = [], start + 1
    while i < len(lines) and not lines[i].startswith("## "):
        if lines[i].strip() == "```python":
            j = i + 1
            while lines[j].strip() != "```":
                j += 1
            blocks.append((i + 2, "\n".join(lines[i + 1 : j])))
            i = j
        i += 1
    return blocks


def _code_spans(text):
    """Inline `code` spans of Markdown text (outside the fenced blocks)."""
    prose = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return re.findall(r"`([^`\n]+)`", prose)


def readme_api_uses(text):
    """`(where, dotted name, call)` for every `jaxsh.*` / `solvers.*` the README shows.

    `call` is `(n positional, keyword names)` for a call in the Usage block or in an inline code span that
    parses as Python, else None (a name only).
    """
    uses = []
    for first, code in [(0, c) for c in _code_spans(text)] + usage_blocks_of(text):
        where = f"README.md:{first}" if first else f"README.md `{code}`"
        try:
            tree = ast.parse("\n" * (first - 1 if first else 0) + code.replace("...", "None"))
        except SyntaxError:
            uses += [(where, m, None) for m in NAME.findall(code)]
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and (name := _dotted(node.func)) and name.split(".")[0] in ROOTS:
                line = f"README.md:{node.lineno}" if first else where
                uses.append((line, name, (len(node.args), [k.arg for k in node.keywords])))
            elif isinstance(node, ast.Attribute) and (name := _dotted(node)) and name.split(".")[0] in ROOTS:
                uses.append((f"README.md:{node.lineno}" if first else where, name, None))
    return uses


def api_problems(text):
    """What of the README's `jaxsh.*` / `solvers.*` does not exist or does not bind, as messages."""
    problems = []
    for where, name, call in readme_api_uses(text):
        try:
            obj = _resolve(name)
        except AttributeError:
            problems.append(f"{where}: {name} does not exist")
            continue
        if call is None:
            continue
        n_pos, keywords = call
        try:
            sig = inspect.signature(obj)
        except (TypeError, ValueError):  # no signature to bind against
            continue
        try:
            sig.bind(*([None] * n_pos), **dict.fromkeys(keywords))
        except TypeError as e:
            problems.append(f"{where}: {name}({n_pos} positional, keywords {keywords}) does not bind to {sig}: {e}")
    return sorted(set(problems))


def test_readme_api_names_exist_and_calls_bind():
    text = README.read_text(encoding="utf-8")
    uses = readme_api_uses(text)
    calls = {name for _, name, call in uses if call is not None}
    # the check sees the Usage block's calls and the prose's names and calls
    assert {"jaxsh.real_sh", "jaxsh.io.read_envmap", "jaxsh.render_practical", "solvers.fit_brdf",
            "solvers.factorize", "solvers.fit_sbrdf", "solvers.pad_observations"} <= calls, calls
    assert {"solvers.inverse_lighting_dual", "solvers.fit_brdf_sh", "jaxsh.compile_options"} <= {n for _, n, _ in uses}
    problems = api_problems(text)
    assert not problems, "\n".join(problems)


def test_readme_api_check_fails_on_a_broken_readme():
    """The check above is not vacuous: a renamed function, a wrong keyword, an extra argument each fail it."""
    text = README.read_text(encoding="utf-8")
    for old, new, expect in (("jaxsh.real_sh(dirs, lmax=8)", "jaxsh.real_shh(dirs, lmax=8)", "does not exist"),
                             ("solvers.factorize(obs, lmax=12)", "solvers.factorize(obs, l_max=12)", "does not bind"),
                             ("jaxsh.real_sh(dirs, lmax=8)", "jaxsh.real_sh(dirs, 8, 9)", "does not bind"),
                             ("`solvers.inverse_lighting_dual`", "`solvers.inverse_lighting_duel`", "does not exist"),
                             ("`solvers.pad_observations(obs, bucket=True)`", "`solvers.pad_observations(obs, buckets=True)`",
                              "does not bind")):
        assert old in text, old
        problems = api_problems(text.replace(old, new, 1))
        assert len(problems) == 1 and expect in problems[0], (new, problems)


def _slug(heading):
    """GitHub's anchor of a Markdown heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_readme_paths_and_links_exist():
    text = README.read_text(encoding="utf-8")
    root = README.parent
    links = [s for s in re.findall(r"\]\(([^)\s]+)\)", text) if not re.match(r"[a-z]+:", s)]
    # repository paths the prose names (docs/..., benchmarks/..., ...)
    paths = set(re.findall(r"(?<![\w/.])((?:docs|benchmarks|notebooks|tests|jaxsh|solvers)/[\w./-]*\w)", text))
    assert len(links) >= 3 and {"docs/manifest.md", "docs/conventions.md", "benchmarks/gpu_checks.sh"} <= paths, (links, paths)
    for link in links:
        path, _, anchor = link.partition("#")
        target = root / path
        assert target.exists(), f"README.md links to {link}: {path} is not in the repository"
        if anchor:
            slugs = {_slug(h) for h in re.findall(r"^#+ (.*)$", target.read_text(encoding="utf-8"), flags=re.M)}
            assert anchor in slugs, f"README.md links to {link}: no heading of {path} has the anchor #{anchor}"
    for path in paths:
        assert (root / path).exists(), f"README.md names {path}, which is not in the repository"


def test_readme_make_targets_exist():
    text = README.read_text(encoding="utf-8")
    makefile = (README.parent / "Makefile").read_text(encoding="utf-8")
    targets = set(re.findall(r"^([\w-]+):", makefile, flags=re.M))
    # `make X` in code: inline spans and the ```bash block (not the prose's verb "make")
    bash = "\n".join(re.findall(r"^```bash\n(.*?)^```", text, flags=re.S | re.M))
    named = {m for code in _code_spans(text) + [bash] for m in re.findall(r"(?:^|\s)make ([a-z][\w-]*)", code, flags=re.M)}
    assert {"demo", "test", "test-all", "bench"} <= named, named
    assert named <= targets, named - targets
    # "`make test` runs `pytest -m "not slow" ...`": every option and path of the quoted line is in the recipe
    quoted = re.search(r"`make test` runs `pytest ([^`]*)`", text).group(1).replace('"not slow"', "").split()
    recipe = re.search(r"^test:.*\n\t(.*)$", makefile, flags=re.M).group(1)
    assert '-m "not slow"' in recipe
    assert set(quoted) <= set(recipe.split()), (quoted, recipe)
