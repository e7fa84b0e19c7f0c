"""The output policy of every command, in one place.

* **Checked before any work**, one line naming the path: a long job must not lose its
  result to a bad path found at the end. A file must not be a folder, must end in the
  suffix of its format where the format is fixed (``.npz`` for FEATURES and CLUSTERS), and
  its folder must exist or be creatable and accept a new file. A folder must be creatable
  and writable. Writability is probed by creating and removing a file in the nearest
  folder that exists (which also catches read-only file systems; ``os.access`` does not,
  and as root it says yes to everything); nothing is created by the check, so a refused
  command leaves no empty folder behind.
* **Never replaced unless told**: an existing output file, or a folder that already holds
  files of the kind the command writes, is refused unless the command was given
  ``--overwrite`` (:func:`add_overwrite_option`). Outputs at a default location
  (``./dqm-out/<command>``, used when no path is given) are never refused nor replaced:
  the next free name is taken (``clusters-2.npz``, ``evaluate-2/``) and the command says
  where it wrote.
* **Whole or not at all**: results are written to a temporary name beside the output and
  renamed when complete (:func:`atomic_output`), so an error or a stop signal leaves no
  partial file.

Commands write their results under ``./dqm-out/<command>`` unless told
otherwise, never into the repository's committed docs.
"""
from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterable, Iterator, Optional, Sequence

from .validation import InputError

#: the default output root of commands that write several files
DEFAULT_ROOT = Path("dqm-out")
#: figure formats (matplotlib's Agg, PDF, SVG and PS back-ends)
IMAGE_SUFFIXES = (".png", ".pdf", ".svg", ".svgz", ".jpg", ".jpeg", ".tif", ".tiff", ".webp", ".eps", ".ps")


def default_dir(command: str) -> Path:
    """``./dqm-out/<command>``: where a command writes when no folder is given."""
    return DEFAULT_ROOT / command


OVERWRITE_HELP = "replace existing outputs (default: refuse them, before any work)"


def add_overwrite_option(parser, help: str = OVERWRITE_HELP) -> None:
    """``--overwrite``, the one way to let a command replace existing outputs."""
    parser.add_argument("--overwrite", action="store_true", help=help)


def _nearest_existing(path: Path) -> Path:
    p = path.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def _probe(folder: Path, what: str) -> None:
    """Check that ``folder`` exists or can be created, and accepts a new file; creates nothing."""
    base = _nearest_existing(folder)
    if not base.is_dir():
        if base == folder.absolute():
            raise InputError(f"{what}: {folder} exists and is not a folder")
        raise InputError(f"{what}: {base} is not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=".dqm-write-check-", dir=base)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        if base == folder.absolute():
            raise InputError(f"{what}: cannot write in {folder} ({exc.strerror or exc})") from None
        raise InputError(f"{what}: cannot create the folder {folder} ({exc.strerror or exc})") from None


def free_name(path) -> Path:
    """``path`` if nothing is there, else the first of ``stem-2.suffix``, ``stem-3.suffix``, ... that is free."""
    p = Path(path)
    k = 2
    while p.exists():
        p = Path(path).with_name(f"{Path(path).stem}-{k}{Path(path).suffix}")
        k += 1
    return p


def check_file(path, option: str, suffixes: Optional[Iterable[str]] = None, *, overwrite: bool = False,
               default: bool = False) -> Path:
    """Check that ``path`` can be written as a new file; returns it as a Path.

    ``option`` names the argument in the message (e.g. ``"--out"``); ``suffixes``: the accepted
    file name endings, when the suffix picks a format. An existing file is refused unless
    ``overwrite``; with ``default`` (the command chose the path, not the user) the next free
    name (:func:`free_name`) is returned instead.
    """
    p = Path(path)
    what = f"{option} {path}"
    if p.is_dir():
        raise InputError(f"{what} is a folder; give a file name")
    if suffixes is not None:
        allowed = tuple(s.lower() for s in suffixes)
        if p.suffix.lower() not in allowed:
            raise InputError(f"{what}: unknown format {p.suffix or '(no suffix)'}; use one of {', '.join(allowed)}")
    if p.exists():
        if default:
            p = free_name(p)
        elif not overwrite:
            raise InputError(f"{what} exists; pass --overwrite to replace it, or name another file")
        elif not os.access(p, os.W_OK):
            raise InputError(f"{what}: the file exists and is read-only")
    _probe(p.parent, what)
    return p


def check_distinct(*named) -> None:
    """Refuse two outputs on one path: ``named`` are (option, path) pairs."""
    seen = {}
    for option, path in named:
        other = seen.setdefault(Path(path).absolute().resolve(), option)
        if other != option:
            raise InputError(f"{other} and {option} name one file, {path}; give each its own")


def check_dir(path, option: str, writes: Optional[Sequence[str]] = None, *, overwrite: bool = False,
              default: bool = False) -> Path:
    """Check that files can be written in the folder ``path`` (which need not exist yet); returns it.

    ``writes``: glob patterns of the files the command writes there (default: any file). A
    folder that already holds such a file is refused unless ``overwrite``; with ``default``
    the next free folder name is returned instead. Nothing is created here: the command
    creates the folder when it writes its first file.
    """
    p = Path(path)
    what = f"{option} {path}"
    if p.exists() and not p.is_dir():
        raise InputError(f"{what} is a file; give a folder")
    if p.is_dir() and not overwrite:
        clash = existing(p, writes)
        if clash and default:
            p = free_name(p)
        elif clash:
            more = f" and {len(clash) - 1} more" if len(clash) > 1 else ""
            raise InputError(f"{what} already holds {clash[0].name}{more}, which this command would replace; pass "
                             "--overwrite to replace them, or name another folder")
    _probe(p, what)
    return p


def existing(folder: Path, writes: Optional[Sequence[str]] = None) -> list:
    """The files in ``folder`` that match ``writes`` (glob patterns; None: any entry), sorted."""
    if not folder.is_dir():
        return []
    if writes is None:
        return sorted(folder.iterdir())
    return sorted({f for pattern in writes for f in folder.glob(pattern)})


@contextmanager
def atomic_output(path, mode: int | None = None) -> Iterator[str]:
    """A temporary file beside ``path`` (same suffix), renamed to ``path`` when the block ends, removed if
    it fails or is interrupted: no partial output. The result gets ``mode``, or the permissions of any new
    file (0666 minus the umask; ``mkstemp`` makes 0600)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
    os.close(fd)
    try:
        yield tmp
        if mode is None:
            mask = os.umask(0)
            os.umask(mask)
            mode = 0o666 & ~mask
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_text(path, text: str) -> Path:
    """Write a text result (JSON, Markdown, CSV) whole or not at all (:func:`atomic_output`)."""
    with atomic_output(path) as tmp, open(tmp, "w", encoding="utf-8") as fh:
        fh.write(text)
    return Path(path)
