"""The pure algorithm core: numpy in, numpy out; no I/O, no messaging.

Both the in-process simulator and the multi-process runtime call these functions.
"""
from .clustering import (
    DEFAULT_NEIGHBORS,
    DEFAULT_RATIO_DENSITY,
    DEFAULT_RHO,
    KERNELS,
    PARENT_MODES,
    QuickMatch,
    QuickMatchResult,
    quickmatch,
)
from .events import ChangeSet, ClusterEvent
from .memory import MemoryBudgetError
from .online import OnlineQuickMatch

__all__ = [
    "DEFAULT_NEIGHBORS", "DEFAULT_RATIO_DENSITY", "DEFAULT_RHO", "KERNELS", "PARENT_MODES",
    "ChangeSet", "ClusterEvent", "MemoryBudgetError", "OnlineQuickMatch", "QuickMatch", "QuickMatchResult",
    "quickmatch",
]
