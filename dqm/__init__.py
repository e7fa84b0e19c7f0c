"""dqm: consistent multi-image feature matching with QuickMatch, centralized and distributed."""
from .core import DEFAULT_RHO, OnlineQuickMatch, QuickMatch, QuickMatchResult, quickmatch
from .validation import InputError

__version__ = "0.1.0"

__all__ = ["DEFAULT_RHO", "InputError", "OnlineQuickMatch", "QuickMatch", "QuickMatchResult", "quickmatch",
           "__version__"]
