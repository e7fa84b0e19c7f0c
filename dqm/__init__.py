"""dqm: consistent multi-image feature matching with QuickMatch, centralized and distributed.

The public names load on first use (PEP 562), so that ``import dqm`` -- and the ``dqm``
command, which must own Ctrl-C from its first moment -- does not pay for numpy and the
engine until they are needed.
"""
from .lazy_exports import lazy_exports

__version__ = "0.1.0"

#: public name -> the module that defines it
_PUBLIC = {"DEFAULT_RHO": ".core", "OnlineQuickMatch": ".core", "QuickMatch": ".core",
           "QuickMatchResult": ".core", "quickmatch": ".core", "InputError": ".validation"}

__all__ = sorted(_PUBLIC) + ["__version__"]
__getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
