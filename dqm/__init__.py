"""dqm: consistent multi-image feature matching with QuickMatch, centralized and distributed.

The public names load on first use (PEP 562), so that ``import dqm`` -- and the ``dqm``
command, which must own Ctrl-C from its first moment -- does not pay for numpy and the
engine until they are needed.
"""
import importlib

__version__ = "0.1.0"

#: public name -> the module that defines it
_PUBLIC = {"DEFAULT_RHO": ".core", "OnlineQuickMatch": ".core", "QuickMatch": ".core",
           "QuickMatchResult": ".core", "quickmatch": ".core", "InputError": ".validation"}

__all__ = sorted(_PUBLIC) + ["__version__"]


def __getattr__(name: str):
    if name in _PUBLIC:
        value = getattr(importlib.import_module(_PUBLIC[name], __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'dqm' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_PUBLIC))
