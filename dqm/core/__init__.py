"""The pure algorithm core: numpy in, numpy out; no I/O, no messaging.

Both the in-process simulator and the multi-process runtime call these functions.
The public names (and the submodules) load on first use (PEP 562): a command that
needs only :mod:`dqm.core.params` does not pay for the engine, and nothing pays for
scipy until a function that uses it runs.
"""
from ..lazy_exports import lazy_exports

#: public name -> the submodule that defines it
_PUBLIC = {
    "DEFAULT_NEIGHBORS": ".clustering", "DEFAULT_RATIO_DENSITY": ".clustering", "DEFAULT_RHO": ".clustering",
    "KERNELS": ".clustering", "PARENT_MODES": ".clustering", "QuickMatch": ".clustering",
    "QuickMatchResult": ".clustering", "quickmatch": ".clustering",
    "ChangeSet": ".events", "ClusterEvent": ".events", "MemoryBudgetError": ".memory", "OnlineQuickMatch": ".online",
}

__all__ = sorted(_PUBLIC)
__getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
