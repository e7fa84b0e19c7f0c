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
import logging
import os
import re
import sys
import warnings
from typing import List, Optional, Tuple

from . import __version__, logging_config, signals
from .commands import HelpFormatter
from .process_env import with_env_defaults

#: command name -> the module that holds it (NAME, HELP, add_arguments, run)
COMMANDS = {
    "extract": "dqm.commands.extract",
    "match": "dqm.commands.match",
    "split": "dqm.commands.split",
    "export": "dqm.commands.export",
    "sfm": "dqm.commands.sfm",
    "import": "dqm.commands.importer",
    "demo": "dqm.commands.demo",
    "evaluate": "dqm.commands.evaluate",
    "plot": "dqm.commands.plot",
    "scene": "dqm.commands.scene",
    "run": "dqm.commands.run",
    "router": "dqm.commands.router",
    "agent": "dqm.commands.agent",
    "coordinator": "dqm.commands.coordinator",
    "stream": "dqm.commands.stream",
    "camera": "dqm.commands.camera",
    "experiment": "dqm.commands.experiment",
    "doctor": "dqm.commands.doctor",
}

VERBOSE_HELP = ("more messages on standard error: -v what the command is doing, -vv debugging detail "
                "(default: warnings and errors only)")


class _VersionAction(argparse.Action):
    """``--version``: the version and the tile kernel, loaded only when asked (the kernel needs numpy)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        from .core.native import kernel_description

        print(f"dqm {__version__}, tile kernel: {kernel_description()}")
        parser.exit()


def command_named(argv: List[str]) -> Optional[str]:
    """The sub-command ``argv`` names (its first word that is not an option), when it is one of ours and no
    ``-h`` / ``--help`` comes before it (``dqm --help match`` shows every command)."""
    for a in argv:
        if a in ("-h", "--help"):
            return None
        if not a.startswith("-"):
            return a if a in COMMANDS else None
    return None


def build_parser(only: Optional[str] = None) -> argparse.ArgumentParser:
    """The ``dqm`` parser with every sub-command, or with sub-command ``only`` alone (a command's start-up
    then imports its own module, not every command's)."""
    parser = argparse.ArgumentParser(prog="dqm", description="Consistent multi-image feature matching with QuickMatch.")
    parser.add_argument("--version", action=_VersionAction, help="the version and the tile kernel in use")
    parser.add_argument("-v", "--verbose", action="count", default=0, dest="verbosity", help=VERBOSE_HELP)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, modname in COMMANDS.items():
        if only is not None and name != only:
            continue
        mod = importlib.import_module(modname)
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=(mod.__doc__ or mod.HELP).strip(),
                           formatter_class=HelpFormatter)
        mod.add_arguments(p)
        # -v after the sub-command too; its own --verbose (a line per image in stream and camera) stays its own
        flags = [f for f in ("-v", "--verbose") if f not in p._option_string_actions]
        if flags:
            p.add_argument(*flags, action="count", default=argparse.SUPPRESS, dest="verbosity_after",
                           help=VERBOSE_HELP)
        p.set_defaults(_run=mod.run, _exit_at_once=getattr(mod, "EXIT_AT_ONCE", False))
    return parser


#: options of one command that contradict each other although they set different things
CONTRADICTIONS = (("--quiet", "--verbose"),)
_FLAG_ACTIONS = (argparse._StoreTrueAction, argparse._StoreFalseAction, argparse._StoreConstAction,
                 argparse.BooleanOptionalAction)
_NEGATIVE_VALUE = re.compile(r"^-[0-9.]")


def _command_parser(parser: argparse.ArgumentParser, name: Optional[str]) -> Optional[argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return action.choices.get(name)
    return None


def _innermost(parser: argparse.ArgumentParser, argv: List[str]) -> argparse.ArgumentParser:
    """The parser of the (sub-)command ``argv`` names, as deep as it goes (``dqm export colmap``'s)."""
    while True:
        action = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
        name = next((t for t in argv if action is not None and t in action.choices), None)
        if name is None:
            return parser
        parser, argv = action.choices[name], argv[argv.index(name) + 1:]


def join_negative_values(parser: argparse.ArgumentParser, argv: List[str]) -> List[str]:
    """``--camera-params -1,1,2,3`` as ``--camera-params=-1,1,2,3``: argparse takes a value that starts with
    '-' and is not a plain number for an option; an option that takes one value takes it here."""
    valued = set()
    for sub in [parser] + [a for act in parser._actions if isinstance(act, argparse._SubParsersAction)
                           for a in act.choices.values()]:
        valued.update(opt for act in sub._actions if act.option_strings and act.nargs is None
                      and not isinstance(act, _FLAG_ACTIONS) and not isinstance(act, argparse._CountAction)
                      for opt in act.option_strings)
    out: List[str] = []
    k = 0
    while k < len(argv):
        if argv[k] in valued and k + 1 < len(argv) and _NEGATIVE_VALUE.match(argv[k + 1]):
            out.append(f"{argv[k]}={argv[k + 1]}")
            k += 2
            continue
        out.append(argv[k])
        k += 1
    return out


def parse_command(argv: List[str], option: str) -> argparse.Namespace:
    """``argv`` (a ``dqm`` command line without the program name) parsed as ``dqm`` parses it, for a command that
    runs another (``dqm coordinator --also-agent``): InputError naming ``option``, with argparse's message, where
    it does not parse."""
    from contextlib import redirect_stderr
    from io import StringIO

    from .validation import InputError

    said = StringIO()
    try:
        with redirect_stderr(said):
            args, clash = _parsed(build_parser(only=command_named(argv)), argv)
    except SystemExit:
        lines = [line for line in said.getvalue().splitlines() if line.strip()]
        raise InputError(f"{option}: {lines[-1] if lines else 'not a dqm command line'}") from None
    if clash or not getattr(args, "_run", None):
        raise InputError(f"{option}: {clash or 'not a dqm command line'}")
    return args


def _parsed(parser: argparse.ArgumentParser, argv: List[str]) -> Tuple[argparse.Namespace, Optional[str]]:
    """``argv`` parsed (argparse exits on what does not parse) and the first contradiction among its flags
    (:func:`contradiction`), or None."""
    argv = join_negative_values(parser, argv)
    args, extra = parser.parse_known_args(argv)
    if extra:  # said by the command's own parser, with its usage (argparse's top level says 'dqm: error')
        _innermost(parser, argv).error(f"unrecognized arguments: {' '.join(extra)}")
    sub = _command_parser(parser, getattr(args, "command", None)) if getattr(args, "_run", None) else None
    return args, (contradiction(sub, argv) if sub is not None else None)


def contradiction(sub: argparse.ArgumentParser, argv: List[str]) -> Optional[str]:
    """The first two flags of ``argv`` that contradict each other (``--guided --no-guided``, ``--quiet
    --verbose``), as a message; None when there are none."""
    given = [a.split("=", 1)[0] for a in argv if a.startswith("--")]
    dest_of = {opt: action.dest for action in sub._actions if isinstance(action, _FLAG_ACTIONS)
               for opt in action.option_strings}
    seen: dict = {}
    for opt in given:
        if opt in dest_of:
            first = seen.setdefault(dest_of[opt], opt)
            if first != opt:
                return f"{first} and {opt} contradict each other; give one"
    for a, b in CONTRADICTIONS:
        if a in given and b in given and a in sub._option_string_actions and b in sub._option_string_actions:
            return f"{a} and {b} contradict each other; give one"
    return None


def verbosity(args: argparse.Namespace) -> int:
    """The ``-v`` count, before and after the sub-command together."""
    return getattr(args, "verbosity", 0) + getattr(args, "verbosity_after", 0)


def _one_line_warning(message, category, filename, lineno, file=None, line=None):
    """Warnings reach a CLI user as one plain line, not Python's file:line format."""
    print(f"warning: {str(message).removeprefix('quickmatch: ')}", file=file or sys.stderr)


#: set when Ctrl-C or SIGTERM came while the command modules were importing (``python -m dqm`` then
#: leaves with os._exit: a KeyboardInterrupt raised inside an extension's import makes CPython end
#: itself with SIGINT at exit, whatever code main returned)
interrupted_while_importing = False

#: set by a command whose module says ``EXIT_AT_ONCE = True`` (the runtime's agent and coordinator): once
#: :func:`main` returned, ``python -m dqm`` leaves with os._exit (see :func:`program`)
exit_at_once = False


def main(argv: Optional[List[str]] = None) -> int:
    """Run one ``dqm`` command line; returns its exit code. From its first line a stop (Ctrl-C, SIGTERM) is one
    line and 130 / 143, whatever was running: the imports, the argument parsing or the command."""
    command = "dqm"
    try:
        with_env_defaults(os.environ)  # before numpy loads: OpenBLAS's workers do not spin, no huge pages
        # SIGTERM leaves like Ctrl-C from the first moment: the imports below take a while
        signals.install_sigterm()
        signals.received = None
        argv = list(sys.argv[1:] if argv is None else argv)
        command = f"dqm {command_named(argv)}" if command_named(argv) else "dqm"
        parser = build_parser(only=command_named(argv))
        from . import outputs

        outputs.reset_claims()
        try:
            return _command(parser, argv)
        finally:
            outputs.release_unused()
    except BaseException as exc:
        stop = exc if isinstance(exc, KeyboardInterrupt) else signals.stopped_by_signal()
        if stop is None or isinstance(exc, SystemExit):
            raise
        # a stop before the command ran (imports, parsing): Python may have wrapped it (a class being made
        # during an import: "Error calling __set_name__")
        global interrupted_while_importing
        interrupted_while_importing = True
        print(f"{command}: {signals.word(stop)}", file=sys.stderr)
        return signals.exit_code(stop)


#: the suffixes of a COLMAP database given to dqm match as its input
DATABASE_SUFFIXES = (".db", ".sqlite", ".sqlite3")


def _loads_pycolmap(args: argparse.Namespace) -> bool:
    """Whether the command line will load pycolmap: it is then loaded while the stops are held, so that the
    handler glog installs for SIGTERM as it loads never runs in another thread (:func:`dqm.signals.let_in`)."""
    command = getattr(args, "command", None)
    if command == "sfm" or getattr(args, "preset", None) == "colmap":
        return True
    if command in ("export", "import"):
        return getattr(args, "format", None) == "colmap"
    if command == "match":
        return bool(getattr(args, "into_database", False)) or any(
            str(i).lower().endswith(DATABASE_SUFFIXES) for i in getattr(args, "inputs", None) or ())
    return False


def _command(parser: argparse.ArgumentParser, argv: List[str]) -> int:
    from .validation import InputError

    args, clash = _parsed(parser, argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    if clash:
        print(f"dqm {args.command}: error: {clash}", file=sys.stderr)
        return 2
    warnings.showwarning = _one_line_warning
    logging_config.configure(verbosity(args))
    if _loads_pycolmap(args):  # while the stops are still held: see signals.let_in
        from .vision.colmap import require_pycolmap

        try:
            require_pycolmap()
        except InputError:
            pass  # the command says it, in its words
    signals.let_in()  # the command's modules are loaded, numpy's threads started with the stops held
    global exit_at_once
    exit_at_once = bool(getattr(args, "_exit_at_once", False))
    try:
        args._main, args._parse = main, parse_command  # for a command that runs another (coordinator --also-agent)
        return int(args._run(args) or 0)
    except InputError as exc:
        print(f"dqm {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into a reader that stopped early (| head): not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except KeyboardInterrupt as exc:  # Ctrl-C, and SIGTERM as signals.Terminated
        print(f"dqm {args.command}: {signals.word(exc)}", file=sys.stderr)
        return signals.exit_code(exc)
    except Exception as exc:  # no traceback reaches the user
        stop = signals.stopped_by_signal()
        if stop is not None:  # the signal landed inside a library's lock handling and surfaced as this error
            print(f"dqm {args.command}: {signals.word(stop)}", file=sys.stderr)
            return signals.exit_code(stop)
        if os.environ.get("DQM_TRACEBACK"):
            raise
        print(f"dqm {args.command}: error: {type(exc).__name__}: {exc} (DQM_TRACEBACK=1 shows where)",
              file=sys.stderr)
        return 70


def program() -> None:
    """The ``dqm`` command (and ``python -m dqm``): :func:`main`, then exit with its code.

    After Ctrl-C or SIGTERM (exit 130 / 143: the command has already stopped its children, closed its
    sessions and removed its partial outputs) it leaves with ``os._exit`` once the output is flushed:
    the interpreter's own exit would first wait for worker threads still finishing a native tile (a
    stop then took seconds), and run C++ libraries' static destructors while their threads were
    still running (``terminate called without an active exception``, exit 134, in 3 of 24 Ctrl-C
    during ``dqm experiment localization``). The same after a signal during the imports (see
    :data:`interrupted_while_importing`).

    Also after the runtime's long-lived processes (:data:`exit_at_once`: ``dqm agent``, ``dqm coordinator``),
    whatever their code: they have closed their zenoh sessions, written and closed their outputs and reaped
    their children by then, and the interpreter's teardown (modules, numpy, OpenBLAS's and zenoh's threads)
    costs 15-40 ms of CPU, which on a host with a quarter core was 0.06-0.15 s more before the coordinator's
    process was gone and the job's result in the caller's hands."""
    code = main()
    if exit_at_once or interrupted_while_importing or code in (signals.EXIT_INTERRUPTED, signals.EXIT_TERMINATED):
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    program()
