"""One logging set-up for every command: the ``dqm`` logger tree, quiet by default.

Modules log through ``logging.getLogger("dqm.<package>")`` (``dqm.core``,
``dqm.distributed``, ``dqm.runtime``, ``dqm.vision``, ...). Nothing here runs on
import: a library user's own logging configuration is left alone. The CLI calls
:func:`configure` once with its ``-v`` count: warnings and errors always reach
stderr, ``-v`` adds what a command is doing (INFO), ``-vv`` adds DEBUG.
"""
from __future__ import annotations

import logging
import sys
from typing import Optional

ROOT = "dqm"
_HANDLER_NAME = "dqm-stderr"


def level_for(verbosity: int) -> int:
    """The level a ``-v`` count selects: 0 -> WARNING, 1 -> INFO, 2 or more -> DEBUG."""
    return logging.WARNING if verbosity <= 0 else logging.INFO if verbosity == 1 else logging.DEBUG


def configure(verbosity: int = 0, tag: Optional[str] = None, stream=None) -> logging.Logger:
    """Send the ``dqm`` loggers to stderr at the level ``verbosity`` selects, each line prefixed with
    ``[tag]`` when given (a runtime process names itself: ``[agent 3]``, ``[coordinator]``).
    Calling it again replaces the earlier set-up (idempotent)."""
    root = logging.getLogger(ROOT)
    for h in list(root.handlers):
        if h.get_name() == _HANDLER_NAME:
            root.removeHandler(h)
    handler = logging.StreamHandler(stream or sys.stderr)
    handler.set_name(_HANDLER_NAME)
    handler.setFormatter(logging.Formatter(f"[{tag}] %(message)s" if tag else "%(message)s"))
    root.addHandler(handler)
    root.setLevel(level_for(verbosity))
    root.propagate = False
    return root


def tag_lines(tag: str) -> None:
    """Prefix every line of the ``dqm`` loggers with ``[tag]`` from now on (a runtime process names
    itself once it knows who it is), keeping the level :func:`configure` chose; configures the
    default (quiet) set-up first when nothing was configured."""
    root = logging.getLogger(ROOT)
    mine = [h for h in root.handlers if h.get_name() == _HANDLER_NAME]
    if not mine:
        configure(0, tag)
        return
    for h in mine:
        h.setFormatter(logging.Formatter(f"[{tag}] %(message)s"))
