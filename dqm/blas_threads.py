"""OpenBLAS's own worker threads in dqm's processes: told to sleep at once after work.

After ``import numpy`` and after every multi-threaded BLAS call, OpenBLAS's workers busy-wait for about
2^28 cycles before they sleep. The engine does not use those workers: its tiles call BLAS single-threaded
from its own threads (:func:`dqm.core.pairs.tile_pool`), so the spin only takes CPU from them and from the
other processes of a host. Measured on 2 cores (AMD EPYC Zen 4): ``import numpy`` took 0.13-0.15 CPU-seconds
instead of 0.06-0.07, which in an emulated host's quarter-core quota is 0.3 s of wall time per process start
(graf on 8 such hosts, balanced: 3.7-4.1 s to result instead of 4.1-4.2 s, three runs each); ``dqm match`` on
sacre_coeur's COLMAP database with the whole machine to itself did not change (medians of 8 alternated runs:
1.94 s against 1.88 s). OpenBLAS reads the setting when it loads, so it must be in the environment before
numpy is imported: the ``dqm`` command (an agent or a coordinator started by hand included) sets it for
itself first thing, and the runtime's launcher for every child (``python -m dqm.runtime.gather`` too). A
value the caller's environment already has is kept. A library user's own process is left alone.
"""
from __future__ import annotations

from typing import MutableMapping

#: the environment dqm's processes start with unless it is set: OpenBLAS workers sleep after 2^4 cycles
BLAS_ENV_DEFAULTS = {"OPENBLAS_THREAD_TIMEOUT": "4"}


def with_blas_defaults(env: MutableMapping[str, str]) -> MutableMapping[str, str]:
    """``env`` with :data:`BLAS_ENV_DEFAULTS` where it has no value of its own (changed in place, returned)."""
    for var, value in BLAS_ENV_DEFAULTS.items():
        env.setdefault(var, value)
    return env
