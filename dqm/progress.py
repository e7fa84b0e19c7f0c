"""A dependency-free progress bar: drawn on a terminal, silent when output is piped."""
from __future__ import annotations

import sys
import time
from typing import Callable, Optional, TextIO, Union


class ProgressBar:
    """Callable ``bar(done, total)`` that redraws one line on a TTY and prints nothing otherwise."""

    def __init__(self, label: str, stream: Optional[TextIO] = None, force: Optional[bool] = None,
                 unit: str = ""):
        self.label = label
        self.unit = f" {unit}" if unit else ""
        self.stream = stream if stream is not None else sys.stderr
        tty = getattr(self.stream, "isatty", lambda: False)()
        self.enabled = tty if force is None else force
        self.start = time.perf_counter()
        self._last = 0.0
        self._done = 0
        self._open = False

    def __call__(self, done: int, total: int) -> None:
        if not self.enabled:
            return
        now = time.perf_counter()
        if done < self._done:  # a new stage counting from zero again
            self.start = now
        self._done = done
        if done < total and now - self._last < 0.1:
            return
        self._last = now
        frac = done / total if total else 1.0
        width = 30
        fill = int(round(frac * width))
        elapsed = now - self.start
        eta = elapsed / frac - elapsed if frac > 0 else float("nan")
        self.stream.write(
            f"\r{self.label} [{'#' * fill}{'.' * (width - fill)}] {done:,}/{total:,}{self.unit} "
            f"{elapsed:5.1f}s eta {eta:5.1f}s"
        )
        self._open = True
        if done >= total:
            self.stream.write("\n")
            self._open = False
        self.stream.flush()

    def close(self) -> None:
        if self._open and self.enabled:
            self.stream.write("\n")
            self.stream.flush()
            self._open = False


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
