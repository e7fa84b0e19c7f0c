"""Children that die with their parent: a launcher's processes never outlive it.

``dqm run`` (and the multi-host helpers) start every router, agent and
coordinator through :func:`child_preexec`, which asks Linux to send the child
SIGTERM when its parent dies (``PR_SET_PDEATHSIG``; it survives the ``exec`` of
``ip netns exec``), and sets ``DQM_PARENT_PID``. The child also runs
:func:`watch_parent`: a thread that notices the parent gone (on systems without
the signal, or if the parent died before the signal was armed) and ends the
process, after a grace period for a clean exit, so that even SIGKILL of
``dqm run`` leaves nothing running.
"""
from __future__ import annotations

import ctypes
import logging
import os
import signal
import sys
import threading
import time
from contextlib import contextmanager
from typing import Callable, Iterator, List, Optional

LOG = logging.getLogger("dqm.runtime")

PARENT_ENV = "DQM_PARENT_PID"
_PR_SET_PDEATHSIG = 1


#: the signals a launcher holds while it starts a child (:func:`signals_deferred`)
DEFERRED = (signal.SIGINT, signal.SIGTERM)


@contextmanager
def signals_deferred() -> Iterator[None]:
    """Hold Ctrl-C and SIGTERM while a child process is being started; they arrive right after.

    A Python signal handler that raises inside ``fork`` (its at-fork hooks) is printed and lost,
    and one raised between the fork and the bookkeeping of the child's pid would leave that child
    unknown to the launcher: so the launcher blocks them around ``Popen`` (the child unblocks them
    again in :func:`child_preexec`).
    """
    old = signal.pthread_sigmask(signal.SIG_BLOCK, DEFERRED)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def child_preexec(parent_pid: int):
    """A ``preexec_fn`` for :class:`subprocess.Popen`: unblock the signals the launcher held while
    starting it (:func:`signals_deferred`) and arm the parent-death signal (Linux)."""
    def arm() -> None:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, DEFERRED)
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
        except (OSError, AttributeError):
            pass
        if os.getppid() != parent_pid:  # the parent died before the signal was armed
            os._exit(1)
    return arm


def fork_call(run: Callable[[], int], log_path: Optional[str] = None) -> int:
    """Call ``run()`` in a child forked from this process, which exits with what it returns; returns its pid.

    The child has this process's imports already done (no interpreter to start), writes its output to
    ``log_path`` (else where this process writes), runs in a session of its own and dies with this process
    (the parent-death signal, and ``DQM_PARENT_PID`` for :func:`watch_parent`), as a launcher's children do.
    Fork before this process starts threads that the child would need or opens network sessions: a child has
    only the thread that forked it. Nothing the parent registered to run at exit runs in the child."""
    parent = os.getpid()
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    with signals_deferred():  # a signal between the fork and the child's set-up: delivered once it is set up
        pid = os.fork()
        if pid:
            return pid
        code = 1
        try:
            os.setsid()
            os.environ[PARENT_ENV] = str(parent)
            if log_path:
                fd = os.open(log_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
                os.dup2(fd, 1)
                os.dup2(fd, 2)
                os.close(fd)
            child_preexec(parent)()  # unblocks the signals, arms the parent-death signal
            code = int(run() or 0)
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 1
        except BaseException as exc:  # noqa: BLE001 - the child must not return into the parent's code
            try:
                print(f"dqm: the forked process failed: {type(exc).__name__}: {exc}", file=sys.stderr)
            except BaseException:  # noqa: BLE001
                pass
        finally:
            try:
                sys.stdout.flush()
                sys.stderr.flush()
            finally:
                os._exit(code)
    raise AssertionError("unreachable")  # pragma: no cover


def reap(pid: int, wait_s: float) -> Optional[int]:
    """The exit code of child ``pid`` once it has exited, waiting at most ``wait_s``; None if it still runs
    (it then dies with this process)."""
    deadline = time.monotonic() + wait_s
    while True:
        try:
            done, status = os.waitpid(pid, os.WNOHANG)
        except ChildProcessError:
            return None
        if done:
            return os.waitstatus_to_exitcode(status)
        if time.monotonic() >= deadline:
            return None
        time.sleep(0.01)


def launched_by(parent_pid: int) -> List[int]:
    """Running processes (zombies aside) whose environment says ``parent_pid`` launched them: what a
    launcher would leave behind."""
    tag = f"{PARENT_ENV}={parent_pid}".encode()
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/environ", "rb") as fh:
                if tag not in fh.read().split(b"\0"):
                    continue
            with open(f"/proc/{entry}/stat") as fh:
                if fh.read().rsplit(")", 1)[1].split()[0] != "Z":
                    found.append(int(entry))
        except (OSError, IndexError):
            pass
    return found


def watch_parent(grace_s: float = 3.0, poll_s: float = 0.5) -> None:
    """If started by a launcher (``DQM_PARENT_PID``), end this process once that parent is gone:
    SIGTERM to itself (a clean exit), then a hard exit after ``grace_s``."""
    try:
        parent = int(os.environ.get(PARENT_ENV, "0"))
    except ValueError:
        return
    if parent <= 1:
        return

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_s)
        LOG.warning("the launching process %d is gone; this process ends", parent)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(grace_s)
        os._exit(1)

    threading.Thread(target=watch, name="dqm-lifeline", daemon=True).start()
