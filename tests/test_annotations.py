"""The annotations of the public API evaluate, and the test-suite checks them.

`typing.get_type_hints` evaluates every annotation of every public name of
`jaxsh`, `jaxsh.io` and `solvers` (functions, classes' fields, public methods
and `__init__`): an annotation that raises when evaluated (e.g. two variadic
dimensions, `"*batch n *C"`) is decoration, never a check. The suite runs
under jaxtyping's import hook with beartype (`--jaxtyping-packages` in
`pyproject.toml`); the last tests show that the hook is on.
"""

import inspect
import types
import typing

import jaxtyping
import numpy as np
import pytest

import jaxsh
import jaxsh.io
import solvers

_MODULES = (jaxsh, jaxsh.io, solvers)


def _public_objects():
    for mod in _MODULES:
        for name in sorted(vars(mod)):
            if name.startswith("_"):
                continue
            obj = getattr(mod, name)
            if isinstance(obj, types.ModuleType):
                continue
            # jaxsh.io's own functions, not what it imports (numpy, Path, ...).
            if mod is jaxsh.io and getattr(obj, "__module__", None) != "jaxsh.io":
                continue
            if inspect.isclass(obj):
                yield f"{mod.__name__}.{name}", obj
                for attr, value in vars(obj).items():
                    if attr.startswith("_") and attr != "__init__":
                        continue
                    if isinstance(value, (staticmethod, classmethod)):
                        value = value.__func__
                    if isinstance(value, property):
                        value = value.fget
                    if callable(value):
                        yield f"{mod.__name__}.{name}.{attr}", value
            elif callable(obj):
                yield f"{mod.__name__}.{name}", obj


_PUBLIC = dict(_public_objects())


def test_public_names_found():
    # The walk sees the API (a guard against an empty parametrization).
    for name in ("jaxsh.convolve", "jaxsh.rotate_sh", "jaxsh.GBuffer", "solvers.fit_brdf", "solvers.Lighting.total_sh"):
        assert name in _PUBLIC
    assert len(_PUBLIC) > 150


@pytest.mark.parametrize("name", sorted(_PUBLIC))
def test_annotations_evaluate(name):
    obj = _PUBLIC[name]
    hints = typing.get_type_hints(obj, include_extras=True)
    assert isinstance(hints, dict)


def _hook_on():
    return getattr(jaxsh.real_sh, "__wrapped__", None) is not None


@pytest.mark.skipif(not _hook_on(), reason="run without --jaxtyping-packages")
def test_hook_checks_shapes():
    # `dirs` is "*batch 3": a (4, 2) array is rejected by the annotation itself
    # (not with pytest.raises, which switches the hook off).
    try:
        jaxsh.real_sh(np.zeros((4, 2)), 2)
    except jaxtyping.TypeCheckError as e:
        assert "dirs" in str(e)
    else:
        pytest.fail("the jaxtyping hook did not check `dirs`")
    # ... and numpy input of the right shape is accepted (inputs are ArrayLike).
    y = jaxsh.real_sh(np.array([[0.0, 0.0, 1.0]]), 1)
    assert y.shape == (1, 4)


@pytest.mark.skipif(not _hook_on(), reason="run without --jaxtyping-packages")
def test_value_errors_are_the_library_s():
    # Inside `pytest.raises` the hook is off (tests/conftest.py), so the
    # library's own ValueError, naming the argument, is what is tested.
    with pytest.raises(ValueError, match="dirs"):
        jaxsh.real_sh(np.zeros((4, 2)), 2)
    assert not jaxtyping.config.jaxtyping_disable


def _model_instances():
    dirs = [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]
    yield jaxsh.Lighting(fast_directions=dirs, fast_energy=[[4.0, 4.0, 3.5], [1.0, 1.0, 1.0]])
    yield jaxsh.Lighting(slow_sh=np.ones(9), fast_directions=np.array(dirs), fast_energy=[1.0, 2.0])
    yield jaxsh.Lighting(slow_sh=np.ones((4, 3)))
    yield jaxsh.Lighting(disk_directions=dirs, disk_radius=[0.1, 0.2], disk_radiance=[1.0, 2.0])
    yield jaxsh.TorranceSparrow(0.5, 0.3, None, 0.1)
    yield jaxsh.TorranceSparrow([0.5, 0.4, 0.3], 1, 1.5, 0.2)
    yield jaxsh.TorranceSparrow(np.ones((5, 3)), np.ones((1, 3)), 1.5, np.float32(0.2))


@pytest.mark.parametrize("model", list(_model_instances()), ids=lambda m: type(m).__name__)
def test_model_fields_are_output_arrays(model):
    # The fields of jaxsh.Lighting / jaxsh.TorranceSparrow are converted to JAX
    # arrays (eqx.field converters), so their annotations are output types,
    # true of whatever the README passes (lists, Python numbers, NumPy arrays).
    # (Equinox gives a converted field's `__init__` parameter the type `Any`, so
    # the hook does not check them: this test does.)
    from beartype.door import is_bearable

    hints = typing.get_type_hints(type(model), include_extras=True)
    for name in ("kd", "ks", "mu", "sigma") if isinstance(model, jaxsh.TorranceSparrow) else (
        "slow_sh", "fast_directions", "fast_energy", "disk_directions", "disk_radius", "disk_radiance"
    ):
        value = getattr(model, name)
        assert is_bearable(value, hints[name]), (name, type(value), getattr(value, "shape", None), hints[name])


def test_docstrings_hold_no_control_characters():
    """Every docstring of every module, function, class and method of `jaxsh` and `solvers` (private ones included)
    is free of the control characters that a LaTeX command in a non-raw string becomes (`\\vec` is a vertical tab,
    `\\rho` a carriage return, `\\beta` a backspace, `\\frac` a form feed, `\\alpha` a bell): the docstrings write
    `\\\\vec`. Caught `rbf_fit`'s `$[1, \\vec q]$` and `$\\rho > 0$` (session 41)."""
    import importlib
    import pkgutil

    bad_chars = "\a\b\f\v\r"
    found = []
    for pkg in (jaxsh, solvers):
        for info in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
            mod = importlib.import_module(info.name)
            objs = [(info.name, mod)]
            for name, obj in vars(mod).items():
                if getattr(obj, "__module__", None) != mod.__name__:
                    continue
                objs.append((f"{info.name}.{name}", obj))
                if inspect.isclass(obj):
                    objs += [(f"{info.name}.{name}.{a}", v) for a, v in vars(obj).items() if callable(v)]
            for where, obj in objs:
                doc = getattr(obj, "__doc__", None)
                if isinstance(doc, str) and any(c in doc for c in bad_chars):
                    found.append(where)
    assert not found, found
