"""Thread pools of numerical libraries: one thread per process for evaluation.

numpy-free on purpose: :mod:`studio.cli` sets these variables *before* numpy loads (the
BLAS/OpenMP pools read them once, at import), and :mod:`studio.optimize.optimizer` sets them in
its evaluation workers. With the default pools (one thread per core) evaluation workers
oversubscribe the cores and each evaluation takes several times longer, and in-process
runs each keep a second thread busy and run several times slower (figures:
``docs/optimization.md#hebo-runs``).
"""

from __future__ import annotations

import os

THREAD_VARS: tuple[str, ...] = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
"""Environment variables that size the OpenMP, OpenBLAS and MKL thread pools."""


def single_thread_env(*, keep_user_settings: bool) -> bool:
    """Set every :data:`THREAD_VARS` to 1 in ``os.environ``.

    Args:
        keep_user_settings: leave variables the user already set untouched.

    Returns:
        True if some variable was set.
    """
    changed = False
    for var in THREAD_VARS:
        if keep_user_settings and var in os.environ:
            continue
        if os.environ.get(var) != "1":
            changed = True
        os.environ[var] = "1"
    return changed
