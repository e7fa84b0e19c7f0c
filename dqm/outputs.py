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
* **Claimed, not just checked**: the check at the start cannot see what another run (or the user)
  puts at the name while the command works, so the name is *taken* at the end, by a hard link
  that fails if the name exists (create-if-absent), never by a rename over it. A default name
  then moves on to the next free one (two ``dqm run`` in one folder write ``clusters.npz`` and
  ``clusters-2.npz``); a name the user gave is left as it is, the result is kept under the next
  free name, and the command refuses in one line that says both (:class:`OutputTaken`). Only
  ``--overwrite`` (and the commands that update a file in place, ``--into-database``) replace,
  and a symbolic link is then written through to its target, as COLMAP's own tools do.
  Default folders are taken when checked (created, the next free name if another run was first),
  and given back at exit if nothing was written in them (:func:`release_unused`).

Commands write their results under ``./dqm-out/<command>`` unless told
otherwise, never into the repository's committed docs.
"""
from __future__ import annotations

import json
import math
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


#: how a checked output's name is taken at the end (:func:`atomic_output`): replaced (``--overwrite``), the
#: next free name if taken meanwhile (a default name), or kept as it is, the result going to the next free name
#: with a refusal (a name the user gave)
REPLACE, NEXT_FREE, KEEP = "replace", "next free", "keep"
#: absolute path of a checked file or folder -> (policy, option); a folder's applies to the files in it
_claims: dict[Path, tuple[str, str]] = {}
#: absolute path asked for -> where this process wrote it
_written: dict[Path, Path] = {}
#: default folders this process created when it checked them (given back at exit if still empty)
_created: list[Path] = []


class OutputTaken(InputError):
    """A name the user gave was taken by someone else while the command ran; the result went elsewhere."""


def _absolute(path) -> Path:
    return Path(os.path.abspath(path))


def _claim(path, option: str, overwrite: bool, default: bool) -> None:
    _claims[_absolute(path)] = (REPLACE if overwrite else NEXT_FREE if default else KEEP, option)


def _policy(path) -> tuple[str, Optional[str]]:
    """The policy of ``path`` (its own, or its nearest checked folder's): unchecked paths (library calls) and
    files this process already wrote are replaced."""
    p = _absolute(path)
    if p in _written:  # rewritten where it went
        return REPLACE, None
    for q in (p, *p.parents):
        if q in _claims:
            return _claims[q]
    return REPLACE, None


def reset_claims() -> None:
    """Forget every check and write of this process (each command starts afresh: :func:`dqm.cli.main`)."""
    _claims.clear()
    _written.clear()
    _created.clear()


def release_unused() -> None:
    """Remove the default folders this process created when it checked them and never wrote into (a command
    refused or stopped after its checks leaves no empty folder behind)."""
    for folder in reversed(_created):
        try:
            folder.rmdir()  # only if empty
        except OSError:
            pass
    _created.clear()


def written(path) -> Path:
    """Where this process wrote the output it was asked to write at ``path`` (another name only for a default
    name that another run took meanwhile); ``path`` itself if not written."""
    return _written.get(_absolute(path), Path(path))


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
    if p.exists() or p.is_symlink():
        if default:
            p = free_name(p)
        elif not overwrite:
            raise InputError(f"{what} exists; pass --overwrite to replace it, or name another file")
        elif not os.access(p, os.W_OK):
            raise InputError(f"{what}: the file exists and is read-only")
    _probe(p.parent, what)
    _claim(p, option, overwrite, default)
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
    if default and not overwrite:
        p = _take_folder(p)
    _claim(p, option, overwrite, False)
    return p


def _take_folder(p: Path) -> Path:
    """A default folder taken for this process: created now (``p`` or, if another run created it first, the next
    free name); an existing one (that held none of the command's files when checked) is used as it is."""
    if p.is_dir():
        return p
    p.parent.mkdir(parents=True, exist_ok=True)
    first = p
    while True:
        try:
            p.mkdir()
        except FileExistsError:
            p = free_name(first)
            continue
        _created.append(p)
        return p


def existing(folder: Path, writes: Optional[Sequence[str]] = None) -> list:
    """The files in ``folder`` that match ``writes`` (glob patterns; None: any entry), sorted."""
    if not folder.is_dir():
        return []
    if writes is None:
        return sorted(folder.iterdir())
    return sorted({f for pattern in writes for f in folder.glob(pattern)})


#: the files SQLite keeps beside a database (a temporary database's are removed with it)
SQLITE_SIBLINGS = ("-wal", "-shm", "-journal")


def remove_temporary(tmp) -> None:
    """Remove a temporary output and the files SQLite made beside it, if there."""
    for name in (str(tmp), *(str(tmp) + s for s in SQLITE_SIBLINGS)):
        try:
            os.unlink(name)
        except FileNotFoundError:
            pass


@contextmanager
def atomic_output(path, mode: int | None = None) -> Iterator[str]:
    """A temporary file beside ``path`` (same suffix), given the name ``path`` when the block ends
    (:func:`publish`: by its checked policy), removed if it fails or is interrupted: no partial output. The
    result gets ``mode``, or the permissions of any new file (0666 minus the umask; ``mkstemp`` makes 0600).
    Where the result went: :func:`written`."""
    target = _target(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp" + target.suffix, dir=target.parent)
    os.close(fd)
    try:
        yield tmp
        if mode is None:
            mask = os.umask(0)
            os.umask(mask)
            mode = 0o666 & ~mask
        os.chmod(tmp, mode)
        publish(tmp, path)
    except BaseException:
        remove_temporary(tmp)
        raise


def _target(path) -> Path:
    """Where a result for ``path`` goes: where this process wrote it before, or through a symbolic link to its
    target where the policy replaces."""
    p = _written.get(_absolute(path), Path(path))
    if p.is_symlink() and _policy(p)[0] == REPLACE:
        return Path(os.path.realpath(p))
    return p


def publish(src, path) -> Path:
    """Give the complete file ``src`` (in ``path``'s folder, or one on the same file system) the name ``path``
    by ``path``'s policy (:func:`check_file`, :func:`check_dir`): replaced (through a symbolic link), or taken
    only if free, by a hard link. Returns where it went (also :func:`written`); raises :class:`OutputTaken`
    when a name the user gave was taken meanwhile (the result is then kept under the next free name)."""
    policy, option = _policy(path)
    key = _absolute(path)
    if policy == REPLACE:
        final = _written.get(key, Path(path))
        os.replace(src, _target(path))
        _written[key] = final
        return final
    final = Path(path)
    while not _take(src, final):
        final = free_name(path)
    _written[key] = final
    if final != Path(path) and policy == KEEP:
        raise OutputTaken(f"{option} {path} appeared while this command ran (another run or program made it); it "
                          f"is left as it is, and this result is kept as {final}")
    return final


def _take(src, path: Path) -> bool:
    """Give ``src`` the name ``path`` if nothing has it (create-if-absent); False if something has."""
    try:
        os.link(src, path)
    except FileExistsError:
        return False
    except OSError:  # a file system without hard links: take the name empty, then fill it
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
        except FileExistsError:
            return False
        os.close(fd)
        os.replace(src, path)
        return True
    os.unlink(src)
    return True


def write_text(path, text: str) -> Path:
    """Write a text result (JSON, Markdown, CSV) whole or not at all (:func:`atomic_output`)."""
    with atomic_output(path) as tmp, open(tmp, "w", encoding="utf-8") as fh:
        fh.write(text)
    return Path(path)


def finite(obj):
    """``obj`` (dicts, lists and tuples of them, any depth) with every NaN or infinite float replaced by None, so
    that its JSON is strict: ``NaN`` is not JSON, and tools other than Python's refuse it (jq, browsers)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    return obj


def write_json(path, obj, indent: Optional[int] = 1) -> Path:
    """Write ``obj`` as strict JSON (:func:`finite`: NaN and infinities as null), whole or not at all."""
    return write_text(path, json.dumps(finite(obj), indent=indent, allow_nan=False) + "\n")
