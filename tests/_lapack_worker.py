"""The solvers' programs and batched CPU LAPACK calls, run in a fresh process (tests/test_lapack.py).

Usage: `python tests/_lapack_worker.py DUMP_DIR`. Runs each solver once on a small capture with XLA's HLO dump in
`DUMP_DIR` (the test reads the compiled programs' LAPACK calls from it), then `factorize` and `inverse_lighting` in
two host threads at once, with a deadline: before the solvers kept their LAPACK calls unbatched on a CPU
(`solvers._lapack`) both hung here on a 2-core machine. Prints one JSON line; exits without waiting for a thread
that did not finish.
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time

if __name__ == "__main__":
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + f" --xla_dump_to={sys.argv[1]} --xla_dump_hlo_as_text").strip()

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    import solvers
    from solvers.synthetic import no_sharing_predict
    from tests._scale_worker import TRUTH, make_capture

    obs, lighting = make_capture(size=16, n_views=2, lmax=6)
    brdf = solvers.TorranceSparrow(*(jnp.asarray(TRUTH[k]) for k in ("kd", "ks", "mu", "sigma")))
    # the two-thread run: larger systems (a capture of 16² px hid the hang: its batched calls were too short to meet)
    obs2, _ = make_capture(size=40, n_views=3, lmax=8)
    runs = {
        "inverse_lighting": lambda: solvers.inverse_lighting(obs2, brdf, 8).status,
        "factorize": lambda: solvers.factorize(obs2, 8).status,
    }
    once = {
        "inverse_lighting": lambda: solvers.inverse_lighting(obs, brdf, 4).status,
        "factorize": lambda: solvers.factorize(obs, 4).status,
        "inverse_lighting_dual": lambda: solvers.inverse_lighting_dual(obs, brdf, 8).status,
        "fit_brdf": lambda: solvers.fit_brdf(obs, lighting, refine=True).status,
        "fit_many": lambda: [r.status for r in solvers.fit_many([(obs, lighting)] * 2, refine=True)],
        "fit_brdf_sh": lambda: solvers.fit_brdf_sh(obs, lighting.total_sh(4), 2).status,
        "no_sharing_predict": lambda: no_sharing_predict(
            np.ones((4, 6, 6, 3)), np.tile([0.0, 0.0, 1.0], (6, 6, 1)), np.ones((6, 6), bool),
            np.asarray([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8], [-0.6, 0.0, 0.8]]), np.asarray([[0.0, 0.0, 1.0]])),
    }
    for f in (*once.values(), *runs.values()):
        jax.block_until_ready(f())

    def loop(f):
        for _ in range(3):
            jax.block_until_ready(f())

    threads = [threading.Thread(target=loop, args=(f,), daemon=True) for f in runs.values() for _ in range(2)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=max(1.0, 120.0 - (time.perf_counter() - t0)))
    print(json.dumps({"ran": sorted(once), "threads_finished": not any(t.is_alive() for t in threads),
                      "seconds": time.perf_counter() - t0}), flush=True)
    os._exit(0)
