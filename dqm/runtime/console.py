"""What the operator sees while a distributed job runs: a live table on a terminal.

The coordinator feeds :class:`JobView` with the agents' ``progress`` reports
(phase, features held, bytes sent so far) and with events (a lost agent
process, a restart). On a terminal the table is redrawn in place, one line per
agent, at most four times a second, and events are printed as lines above it.
When the output is not a terminal (piped, a log file) nothing is drawn.

Why not tqdm (which draws the single-job bars in :mod:`dqm.progress`): this is a table of
per-agent states fed by remote reports, written to a file descriptor the launcher hands over,
with event lines printed above it; tqdm's bars count one quantity each and have no such rows.
"""
from __future__ import annotations

import os
import sys
import time
from typing import Dict, Optional, TextIO, Tuple


def _mb(n: int) -> str:
    return f"{n / 1e6:8.2f} MB"


class JobView:
    def __init__(self, stream: TextIO, m: int, min_interval_s: float = 0.25):
        self.stream = stream
        self.m = m
        self.min_interval_s = min_interval_s
        self.rows: Dict[int, Tuple[int, str, int, int]] = {}
        self.t0 = time.monotonic()
        self._drawn = 0
        self._last = 0.0
        self.epoch = 0

    @classmethod
    def for_fd(cls, fd: Optional[int], m: int) -> Optional["JobView"]:
        """A view on file descriptor ``fd`` (default: standard error), or None if that is not a terminal."""
        try:
            stream = sys.stderr if fd is None else os.fdopen(fd, "w", buffering=1, closefd=False)
        except OSError:
            return None
        return cls(stream, m) if getattr(stream, "isatty", lambda: False)() else None

    def update(self, agent: int, host: int, state: str, features: int, sent: int) -> None:
        self.rows[agent] = (host, state[5:] if state.startswith("wait_") else state, features, sent)
        if time.monotonic() - self._last >= self.min_interval_s:
            self.draw()

    def event(self, text: str) -> None:
        self._clear()
        self.stream.write(f"[coordinator] {text}\n")
        self.rows = {}
        self.draw()

    def _clear(self) -> None:
        if self._drawn:
            self.stream.write(f"\x1b[{self._drawn}F" + "\x1b[2K\n" * self._drawn + f"\x1b[{self._drawn}F")
            self._drawn = 0

    def lines(self):
        done = sum(1 for r in self.rows.values() if r[1] in ("finish", "acks"))
        total = sum(r[3] for r in self.rows.values())
        yield (f"dqm job: {time.monotonic() - self.t0:6.1f} s, {done}/{self.m} agents done, "
               f"{_mb(total).strip()} sent")
        for a in range(self.m):
            if a in self.rows:
                host, state, feats, sent = self.rows[a]
                where = "" if host == a else f" (on process {host})"
                yield f"  agent {a:<3} {state:<12} {feats:>10,} features {_mb(sent)}{where}"
            else:
                yield f"  agent {a:<3} {'waiting':<12}"

    def draw(self) -> None:
        self._last = time.monotonic()
        out = [f"\x1b[{self._drawn}F"] if self._drawn else []
        lines = list(self.lines())
        out += ["\x1b[2K" + line + "\n" for line in lines]
        self.stream.write("".join(out))
        self.stream.flush()
        self._drawn = len(lines)

    def close(self) -> None:
        self.draw()
        self._drawn = 0
