"""The pure algorithm core: numpy in, numpy out; no I/O, no messaging.

Both the in-process simulator and the multi-process runtime call these functions.
The public names (and the submodules) load on first use (PEP 562): a command that
needs only :mod:`dqm.core.params` does not pay for the engine, and nothing pays for
scipy until a function that uses it runs.
"""
import importlib

#: public name -> the submodule that defines it
_PUBLIC = {
    "DEFAULT_NEIGHBORS": "clustering", "DEFAULT_RATIO_DENSITY": "clustering", "DEFAULT_RHO": "clustering",
    "KERNELS": "clustering", "PARENT_MODES": "clustering", "QuickMatch": "clustering",
    "QuickMatchResult": "clustering", "quickmatch": "clustering",
    "ChangeSet": "events", "ClusterEvent": "events", "MemoryBudgetError": "memory", "OnlineQuickMatch": "online",
}

__all__ = sorted(_PUBLIC)


def __getattr__(name: str):
    if name in _PUBLIC:
        value = getattr(importlib.import_module(f".{_PUBLIC[name]}", __name__), name)
    else:
        try:
            value = importlib.import_module(f".{name}", __name__)  # dqm.core.<submodule>
        except ModuleNotFoundError as exc:
            if exc.name != f"{__name__}.{name}":
                raise  # the submodule exists; something it imports is missing
            raise AttributeError(f"module 'dqm.core' has no attribute {name!r}") from None
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_PUBLIC))
