"""Output paths of the commands: checked before any work, one line naming the path.

A long job must not lose its result to a bad path found at the end, so every
command checks its outputs first. A file must not be a folder, must have a
known format where the suffix picks one, and its folder must exist or be
creatable and accept a new file. A folder must be creatable and writable.
Writability is probed by creating and removing a file, which also catches
read-only file systems (``os.access`` does not, and as root it says yes to
everything).

Commands write their results under ``./dqm-out/<command>`` unless told
otherwise, never into the repository's committed docs.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Iterable, Optional

from .validation import InputError

#: the default output root of commands that write several files
DEFAULT_ROOT = Path("dqm-out")
#: figure formats (matplotlib's Agg, PDF, SVG and PS back-ends)
IMAGE_SUFFIXES = (".png", ".pdf", ".svg", ".svgz", ".jpg", ".jpeg", ".tif", ".tiff", ".webp", ".eps", ".ps")


def default_dir(command: str) -> Path:
    """``./dqm-out/<command>``: where a command writes when no folder is given."""
    return DEFAULT_ROOT / command


def _probe(folder: Path, what: str) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise InputError(f"{what}: {folder} exists and is not a folder") from None
    except OSError as exc:
        raise InputError(f"{what}: cannot create the folder {folder} ({exc.strerror or exc})") from None
    if not folder.is_dir():
        raise InputError(f"{what}: {folder} is not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=".dqm-write-check-", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise InputError(f"{what}: cannot write in {folder} ({exc.strerror or exc})") from None


def check_file(path, option: str, suffixes: Optional[Iterable[str]] = None) -> Path:
    """Check that ``path`` can be written as a file; returns it as a Path.

    ``option`` names the argument in the message (e.g. ``"--out"``);
    ``suffixes``: the accepted file name endings, when the suffix picks a format.
    """
    p = Path(path)
    what = f"{option} {path}"
    if p.is_dir():
        raise InputError(f"{what} is a folder; give a file name")
    if suffixes is not None:
        allowed = tuple(s.lower() for s in suffixes)
        if p.suffix.lower() not in allowed:
            raise InputError(f"{what}: unknown format {p.suffix or '(no suffix)'}; use one of {', '.join(allowed)}")
    if p.exists() and not os.access(p, os.W_OK):
        raise InputError(f"{what}: the file exists and is read-only")
    _probe(p.parent, what)
    return p


def check_dir(path, option: str) -> Path:
    """Create ``path`` if needed and check that files can be written in it; returns it as a Path."""
    p = Path(path)
    _probe(p, f"{option} {path}")
    return p
