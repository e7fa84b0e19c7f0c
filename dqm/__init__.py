"""dqm: consistent multi-image feature matching with QuickMatch, centralized and distributed.

The public names load on first use (PEP 562), so that ``import dqm`` -- and the ``dqm``
command, which must own Ctrl-C from its first moment -- does not pay for numpy and the
engine until they are needed.
"""


def _own_stops_from_the_start() -> None:
    """In the ``dqm`` command (its console script or ``python -m dqm``), from this package's first line until the
    CLI has its signal policy: Ctrl-C and SIGTERM are held back (:func:`dqm.cli.main` lets them in,
    :func:`dqm.signals.let_in`, and a stop that came is then one line and 130 / 143). A program that imports dqm
    keeps its own mask."""
    import os
    import sys

    argv = getattr(sys, "orig_argv", [])
    if os.path.basename(sys.argv[0] if sys.argv else "") != "dqm" and argv[1:3] != ["-m", "dqm"]:
        return
    import signal

    # held back until dqm.cli.main has its handlers and the command's modules (numpy, OpenBLAS) are loaded:
    # the native threads started meanwhile inherit the mask, so a stop reaches the main thread only, never a
    # native library's handler run in one of its threads (pycolmap's glog takes SIGTERM when it loads)
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})


_own_stops_from_the_start()

from .lazy_exports import lazy_exports  # noqa: E402 - after the stops are held: the command owns Ctrl-C first

__version__ = "0.1.0"

#: public name -> the module that defines it
_PUBLIC = {"DEFAULT_RHO": ".core", "OnlineQuickMatch": ".core", "QuickMatch": ".core",
           "QuickMatchResult": ".core", "quickmatch": ".core", "InputError": ".validation"}

__all__ = sorted(_PUBLIC) + ["__version__"]
__getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
