"""Progress for long work: a tqdm bar on a terminal, nothing when output is piped.

The engine reports progress as ``callback(done, total)``, so the core stays free of any display
library; :class:`ProgressBar` adapts that callback to tqdm, which does the drawing, rate and ETA.
tqdm is imported when a bar is first drawn: its import (about 15 ms, most of it ``importlib.metadata``
for its version) is in every process that imports the engine, and most of them never draw one.
"""
from __future__ import annotations

import sys
from typing import TYPE_CHECKING, Callable, Optional, TextIO, Union

if TYPE_CHECKING:
    from tqdm import tqdm


def _where(stream: Optional[TextIO], force: Optional[bool]) -> tuple:
    """``(stream, draws)`` of a progress display: the stream (default standard error) and whether to draw on it (a
    terminal; ``force`` overrides the test)."""
    stream = stream if stream is not None else sys.stderr
    tty = getattr(stream, "isatty", lambda: False)()
    return stream, tty if force is None else force


class ProgressBar:
    """Callable ``bar(done, total)`` drawn with tqdm on a TTY; silent otherwise.

    ``force`` overrides the terminal test (``True`` draws into any stream, ``False`` never draws).
    A call whose ``done`` is below the previous one starts a new stage: the bar resets.
    """

    def __init__(self, label: str, stream: Optional[TextIO] = None, force: Optional[bool] = None,
                 unit: str = ""):
        self.label = label
        self.unit = unit or "it"
        self.stream, self.enabled = _where(stream, force)
        self._bar: Optional["tqdm"] = None
        self._done = 0

    def __call__(self, done: int, total: int) -> None:
        if not self.enabled:
            return
        if self._bar is None or done < self._done:
            from tqdm import tqdm

            self.close()
            self._bar = tqdm(total=total, desc=self.label, unit=self.unit, file=self.stream,
                             dynamic_ncols=True, mininterval=0.1, leave=True)
            self._done = 0
        elif self._bar.total != total:
            self._bar.total = total
        self._bar.update(done - self._done)
        self._done = done
        if done >= total:
            self.close()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


ProgressArg = Union[None, bool, Callable[[int, int], None]]


def resolve_progress(progress: ProgressArg, label: str, unit: str = "") -> Optional[Callable[[int, int], None]]:
    """``True`` -> a terminal bar, ``False``/``None`` -> nothing, a callable -> itself."""
    if progress is True:
        return ProgressBar(label, unit=unit)
    if progress is None or progress is False:
        return None
    if callable(progress):
        return progress
    raise TypeError(f"progress must be a bool or a callable(done, total), got {progress!r}")


class Ticker:
    """``with Ticker(label):`` one line on a TTY with the label and the time since the block began, redrawn
    every ``every`` seconds by a thread of its own until the block ends: the progress of a long call that
    reports none (COLMAP's global mapper, triangulator and bundle adjustment). Silent otherwise, as
    :class:`ProgressBar` (``force`` overrides the terminal test). The thread ends with the block, however it
    ends."""

    def __init__(self, label: str, stream: Optional[TextIO] = None, force: Optional[bool] = None,
                 every: float = 1.0):
        self.label = label
        self.every = float(every)
        self.stream, self.enabled = _where(stream, force)
        self._bar: Optional["tqdm"] = None
        self._thread = None
        self._stop = None

    def __enter__(self) -> "Ticker":
        if not self.enabled:
            return self
        import threading

        from tqdm import tqdm

        self._bar = tqdm(total=None, desc=self.label, bar_format="{desc}: {elapsed} elapsed", file=self.stream,
                         dynamic_ncols=True, leave=True)
        self._stop = threading.Event()
        stop, bar = self._stop, self._bar

        def redraw() -> None:
            while not stop.wait(self.every):
                bar.refresh()

        self._thread = threading.Thread(target=redraw, name="dqm-ticker", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        if self._bar is None:
            return
        self._stop.set()
        self._thread.join()
        self._bar.close()
        self._bar = None


def ticking(progress: ProgressArg, label: str):
    """A :class:`Ticker` for ``label`` where ``progress`` draws on a terminal (``True``, or a
    :class:`ProgressBar` that draws: on its stream), else a context that shows nothing: what a function that
    takes :data:`ProgressArg` shows around a call that reports no counts."""
    import contextlib

    if progress is True:
        return Ticker(label)
    if isinstance(progress, ProgressBar) and progress.enabled:
        return Ticker(label, stream=progress.stream, force=True)
    return contextlib.nullcontext()
