"""The signal policy of every command, in one place.

Ctrl-C (SIGINT) and SIGTERM stop any ``dqm`` command in every state (starting, connecting,
waiting, computing, writing): it exits with 130 after SIGINT and 143 after SIGTERM, the shell's
codes, with one line and no traceback, its child processes stopped and its outputs either
complete or absent (:func:`dqm.outputs.atomic_output`).

* SIGTERM is raised as :class:`Terminated`, a ``KeyboardInterrupt``: every ``except
  KeyboardInterrupt`` that cleans up after Ctrl-C cleans up after SIGTERM too, and
  :func:`exit_code` and :func:`word` tell the two apart.
* Commands that finish their current item before stopping (``dqm stream``, ``dqm camera``)
  catch both signals in a :class:`StopFlag`; loops that wait (connecting to a router, retries)
  call :meth:`StopFlag.check`, which raises as the default handlers would.
"""
from __future__ import annotations

import contextlib
import signal
from typing import Optional

EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143

#: the last stop signal this process received (None: none). A signal that lands inside a library's lock
#: handling can surface as another error (``RuntimeError: release unlocked lock``); the CLI reads this to
#: report the stop for what it was.
received: Optional[int] = None


class Terminated(KeyboardInterrupt):
    """SIGTERM: leave like Ctrl-C (children stopped, files closed), exit 143."""


def raise_terminated(signum, frame):
    """The SIGTERM handler: raise :class:`Terminated` in the main thread."""
    global received
    received = signal.SIGTERM
    raise Terminated()


def raise_interrupted(signum, frame):
    """The SIGINT handler: Python's own (``KeyboardInterrupt``), remembering that it came."""
    global received
    received = signal.SIGINT
    raise KeyboardInterrupt


def install_sigterm(force: bool = False) -> None:
    """Make SIGTERM raise :class:`Terminated` (unless a handler other than the default is set and not ``force``),
    and SIGINT raise ``KeyboardInterrupt`` even when the process started with SIGINT ignored (as a shell
    script's background jobs do): a dqm command obeys Ctrl-C whoever started it."""
    if force or signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, None):
        signal.signal(signal.SIGTERM, raise_terminated)
    if signal.getsignal(signal.SIGINT) in (signal.SIG_IGN, signal.SIG_DFL, None, signal.default_int_handler):
        signal.signal(signal.SIGINT, raise_interrupted)


def let_in() -> None:
    """Let in the stops that ``dqm/__init__.py`` held back in the ``dqm`` command (one that came meanwhile is
    raised now, by the handlers :func:`install_sigterm` set); nothing where none were held. The CLI calls it
    once the command line is parsed and its modules loaded, pycolmap too where the command will use it: every
    native thread started by then (numpy's, pycolmap's) has them held for good, so that a stop reaches the main
    thread, and a handler a native library installs (glog's, for SIGTERM) cannot run in one of its threads."""
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})


def exit_code(exc: BaseException) -> int:
    """143 for :class:`Terminated`, 130 for any other ``KeyboardInterrupt``."""
    return EXIT_TERMINATED if isinstance(exc, Terminated) else EXIT_INTERRUPTED


def word(exc: BaseException) -> str:
    """``"terminated"`` or ``"interrupted"``, for the one line a stopped command prints."""
    return "terminated" if isinstance(exc, Terminated) else "interrupted"


def stopped_by_signal() -> Optional[KeyboardInterrupt]:
    """The stop that came, as the exception it was raised as (None if no signal came): for an error that a
    signal caused inside a library (it landed in the library's lock handling)."""
    if received is None:
        return None
    return Terminated() if received == signal.SIGTERM else KeyboardInterrupt()


class StopFlag:
    """A signal handler that records SIGINT / SIGTERM instead of raising (the current item is finished
    first); a second Ctrl-C raises at once. :meth:`check` raises for a recorded signal."""

    def __init__(self):
        self.signal: Optional[int] = None

    def __call__(self, signum, frame):
        global received
        received = signum
        if self.signal == signal.SIGINT and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.signal = signum

    def __bool__(self) -> bool:
        return self.signal is not None

    def check(self) -> None:
        """Raise ``KeyboardInterrupt`` (SIGINT) or :class:`Terminated` (SIGTERM) if one came."""
        if self.signal == signal.SIGTERM:
            raise Terminated()
        if self.signal is not None:
            raise KeyboardInterrupt

    def exit_code(self) -> int:
        return EXIT_INTERRUPTED if self.signal == signal.SIGINT else EXIT_TERMINATED

    def install(self) -> dict:
        """Handle both signals; returns the previous handlers (for :func:`restore`)."""
        return {s: signal.signal(s, self) for s in (signal.SIGINT, signal.SIGTERM)}


def restore(handlers: dict) -> None:
    """Put back the handlers :meth:`StopFlag.install` returned."""
    for s, h in handlers.items():
        signal.signal(s, h)


def reassert() -> None:
    """Give SIGINT and SIGTERM back to the handlers Python has for them, at the C level: a native library may
    install its own when it loads (pycolmap's glog prints a stack dump and dies on SIGTERM), and Python does
    not notice. Only from the main thread (where handlers are set); elsewhere it does nothing."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return
    for s in (signal.SIGINT, signal.SIGTERM):
        handler = signal.getsignal(s)
        if handler is not None:
            signal.signal(s, handler)


@contextlib.contextmanager
def held():
    """Hold SIGINT and SIGTERM back in this thread while the block runs, and let a held one in after it: for a
    native library's import that installs its own handler partway (pycolmap's glog takes SIGTERM early in its
    import; the block ends with :func:`reassert`)."""
    before = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


#: how often the main thread looks up from a native call it waits for (:func:`interruptible`)
WAKE_S = 0.1


def interruptible(fn, *args, **kwargs):
    """``fn(*args, **kwargs)`` in a worker thread, the main thread waiting for it in steps of :data:`WAKE_S`, so
    that a stop reaches Python's handlers while a long native call (one that releases the GIL: pycolmap's
    extraction, matching, verification, mapping) runs: the ``KeyboardInterrupt`` is raised here at once, its
    cleanup runs, and the call is left behind (the CLI then leaves with os._exit, which ends it). Returns what
    ``fn`` returns, raises what it raises. Off the main thread it simply calls ``fn``."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return fn(*args, **kwargs)
    box: dict = {}

    def work():
        try:
            box["value"] = fn(*args, **kwargs)
        except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread, raised there
            box["error"] = exc

    worker = threading.Thread(target=work, name=f"dqm-native-{getattr(fn, '__name__', 'call')}", daemon=True)
    worker.start()
    while worker.is_alive():
        worker.join(WAKE_S)
    if "error" in box:
        raise box["error"]
    return box.get("value")
