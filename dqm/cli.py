"""The ``dqm`` command line: one sub-command per stage (see ``dqm --help``).

Each sub-command lives in its own module under :mod:`dqm.commands` and exposes
``NAME``, ``HELP``, ``add_arguments(parser)`` and ``run(args) -> int``.
Errors in the user's input print one line naming the problem and exit with 2;
Ctrl-C exits with 130, SIGTERM with 143; no Python traceback reaches the user
(an unexpected error prints one line; DQM_TRACEBACK=1 shows the traceback).
Messages go through the ``dqm`` loggers (:mod:`dqm.logging_config`): warnings by
default, ``-v`` adds what a command is doing, ``-vv`` debugging detail; ``-v``
goes before the sub-command or after it (``dqm -v evaluate``, ``dqm evaluate -v``).
"""
from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
import warnings
from typing import List, Optional

from . import __version__, logging_config
from .commands import HelpFormatter

COMMANDS = [
    "dqm.commands.extract",
    "dqm.commands.match",
    "dqm.commands.split",
    "dqm.commands.export",
    "dqm.commands.sfm",
    "dqm.commands.importer",
    "dqm.commands.demo",
    "dqm.commands.evaluate",
    "dqm.commands.plot",
    "dqm.commands.scene",
    "dqm.commands.run",
    "dqm.commands.router",
    "dqm.commands.agent",
    "dqm.commands.coordinator",
    "dqm.commands.stream",
    "dqm.commands.camera",
    "dqm.commands.experiment",
    "dqm.commands.doctor",
]

VERBOSE_HELP = ("more messages on standard error: -v what the command is doing, -vv debugging detail "
                "(default: warnings and errors only)")


def build_parser() -> argparse.ArgumentParser:
    """The ``dqm`` parser with every sub-command (imports the command modules and what they need)."""
    from .core.native import kernel_description

    parser = argparse.ArgumentParser(prog="dqm", description="Consistent multi-image feature matching with QuickMatch.")
    parser.add_argument("--version", action="version", version=f"dqm {__version__}, tile kernel: "
                        f"{kernel_description()}")
    parser.add_argument("-v", "--verbose", action="count", default=0, dest="verbosity", help=VERBOSE_HELP)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for modname in COMMANDS:
        mod = importlib.import_module(modname)
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=(mod.__doc__ or mod.HELP).strip(),
                           formatter_class=HelpFormatter)
        mod.add_arguments(p)
        # -v after the sub-command too; its own --verbose (a line per image in stream and camera) stays its own
        flags = [f for f in ("-v", "--verbose") if f not in p._option_string_actions]
        if flags:
            p.add_argument(*flags, action="count", default=argparse.SUPPRESS, dest="verbosity_after",
                           help=VERBOSE_HELP)
        p.set_defaults(_run=mod.run)
    return parser


def verbosity(args: argparse.Namespace) -> int:
    """The ``-v`` count, before and after the sub-command together."""
    return getattr(args, "verbosity", 0) + getattr(args, "verbosity_after", 0)


class Terminated(KeyboardInterrupt):
    """SIGTERM: leave like Ctrl-C (children stopped, files closed), exit 143."""


def _on_sigterm(signum, frame):
    raise Terminated()


def _one_line_warning(message, category, filename, lineno, file=None, line=None):
    """Warnings reach a CLI user as one plain line, not Python's file:line format."""
    print(f"warning: {str(message).removeprefix('quickmatch: ')}", file=file or sys.stderr)


#: set when Ctrl-C or SIGTERM came while the command modules were importing (``python -m dqm`` then
#: leaves with os._exit: a KeyboardInterrupt raised inside an extension's import makes CPython end
#: itself with SIGINT at exit, whatever code main returned)
interrupted_while_importing = False


def main(argv: Optional[List[str]] = None) -> int:
    # SIGTERM leaves like Ctrl-C from the first moment: the imports below take a while
    if signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, None):
        signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        parser = build_parser()
        from .validation import InputError
    except KeyboardInterrupt as exc:
        global interrupted_while_importing
        interrupted_while_importing = True
        print(f"dqm: {'terminated' if isinstance(exc, Terminated) else 'interrupted'}", file=sys.stderr)
        return 143 if isinstance(exc, Terminated) else 130
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    warnings.showwarning = _one_line_warning
    logging_config.configure(verbosity(args))
    try:
        return int(args._run(args) or 0)
    except InputError as exc:
        print(f"dqm {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into a reader that stopped early (| head): not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except Terminated:
        print(f"dqm {args.command}: terminated", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print(f"dqm {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - no traceback reaches the user
        if os.environ.get("DQM_TRACEBACK"):
            raise
        print(f"dqm {args.command}: error: {type(exc).__name__}: {exc} (DQM_TRACEBACK=1 shows where)",
              file=sys.stderr)
        return 70


def program() -> None:
    """The ``dqm`` command (and ``python -m dqm``): :func:`main`, then exit with its code. After a
    signal during the imports it leaves with ``os._exit`` (see :data:`interrupted_while_importing`)."""
    code = main()
    if interrupted_while_importing:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    program()
