"""The environment dqm's processes start with: settings read once, when OpenBLAS and numpy load.

**OpenBLAS's worker threads sleep at once after work.** After ``import numpy`` and after every multi-threaded
BLAS call, OpenBLAS's workers busy-wait for about 2^28 cycles before they sleep. The engine does not use those
workers: its tiles call BLAS single-threaded from its own threads (:func:`dqm.core.pairs.tile_pool`), so the
spin only takes CPU from them and from the other processes of a host. Measured on 2 cores (AMD EPYC Zen 4):
``import numpy`` took 0.13-0.15 CPU-seconds instead of 0.06-0.07, which in an emulated host's quarter-core
quota is 0.3 s of wall time per process start (graf on 8 such hosts, balanced: 3.7-4.1 s to result instead of
4.1-4.2 s, three runs each); ``dqm match`` on sacre_coeur's COLMAP database with the whole machine to itself
did not change (medians of 8 alternated runs: 1.94 s against 1.88 s).

**numpy does not ask for transparent huge pages.** numpy advises the kernel to back every array of 4 MB or more
with 2 MB pages (``madvise(MADV_HUGEPAGE)``). Where the kernel's setting is ``madvise`` (the common default),
each first touch of such a page then zeroes 2 MB, and may compact memory first, whatever part of it the array
uses; the engines make many short-lived arrays of that size (fancy-indexed gathers, per-block operands).
Measured on 2 cores (AMD EPYC Zen 4, THP ``madvise``, defrag ``madvise``), `dqm match` of sacre_coeur's 90k
COLMAP features into its database, 10 runs each alternated: wall median 3.09 -> 2.87 s (fastest 2.90 ->
2.62 s), system time 0.66 -> 0.41 s (twice the page faults, each far cheaper); the exact engine on the same
features 4.80 -> 4.69 s (6 runs each).

Both are read when the libraries load, so they must be in the environment before numpy is imported: the
``dqm`` command (an agent or a coordinator started by hand included) sets them for itself first thing, and the
runtime's launcher for every child (``python -m dqm.runtime.gather`` too). A value the caller's environment
already has is kept. A library user's own process is left alone.
"""
from __future__ import annotations

from typing import MutableMapping

#: the environment dqm's processes start with unless it is set: OpenBLAS workers sleep after 2^4 cycles, numpy
#: makes no huge-page requests
ENV_DEFAULTS = {"OPENBLAS_THREAD_TIMEOUT": "4", "NUMPY_MADVISE_HUGEPAGE": "0"}


def with_env_defaults(env: MutableMapping[str, str]) -> MutableMapping[str, str]:
    """``env`` with :data:`ENV_DEFAULTS` where it has no value of its own (changed in place, returned)."""
    for var, value in ENV_DEFAULTS.items():
        env.setdefault(var, value)
    return env
