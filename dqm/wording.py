"""Wording shared by the messages of every command."""
from __future__ import annotations

from typing import Optional


def count(n: int, noun: str, plural: Optional[str] = None) -> str:
    """``"1 image"``, ``"2 images"``, ``"1,024 features"``: a number and its noun, in agreement."""
    word = noun if n == 1 else (plural or noun + "s")
    return f"{n:,} {word}" if abs(n) >= 10_000 else f"{n} {word}"


def seconds(s: float) -> str:
    """A duration the user gave or waited, without rounding it to a wrong ``0 s``: ``0.5 s``, ``12 s``, ``2.5 s``."""
    return f"{s:.3g} s" if s < 100 else f"{s:.0f} s"
