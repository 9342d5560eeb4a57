"""The runtime type checker that jaxtyping's import hook applies to `jaxsh` and `solvers`.

beartype with the PEP 484 numeric tower (`int` is accepted for `float`, and
`float` for `complex`, as static checkers do), so that `radius: float = 1` is
not a failure. Named in pyproject's `--jaxtyping-packages=...,tests._typecheck.typechecker`
because jaxtyping 0.3.11's plugin cannot split a package list followed by a
typechecker call with arguments (`beartype.beartype(conf=...)`): with
parentheses it splits at the first comma only. `tests/conftest.py` imports
this module before anything imports `jaxsh`.
"""

from beartype import BeartypeConf, beartype

typechecker = beartype(conf=BeartypeConf(is_pep484_tower=True))
