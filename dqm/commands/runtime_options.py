"""Options shared by the runtime commands (algorithm parameters, TLS)."""
from __future__ import annotations

from typing import Optional, get_type_hints

from ..distributed.config import DQMConfig, algorithm_fields, config_args
from .param_options import add_field_option

__all__ = ["add_algorithm", "add_tls", "algorithm_fields", "check_pem", "config_args", "config_from", "tls_from"]


def _metavar(flag: str) -> str:
    return flag.lstrip("-").upper().replace("-", "_")


def add_algorithm(p) -> None:
    """The algorithm options, one per :class:`DQMConfig` field (:func:`algorithm_fields`): flag, help,
    choices and default from the field's metadata and default, the type from its annotation; a tri-state
    flag (``cell_weights``) gets a ``--x`` / ``--no-x`` pair whose default None leaves it to the mode."""
    g = p.add_argument_group("algorithm (must be the same for every agent of a job)")
    types = get_type_hints(DQMConfig)
    for f in algorithm_fields():
        m = f.metadata
        if "negation" in m:
            g.add_argument(m["flag"], dest=f.name, action="store_true", default=f.default, help=m["help"])
            g.add_argument(m["negation"], dest=f.name, action="store_false", default=f.default,
                           help=m["negation_help"])
            continue
        add_field_option(g, f, types[f.name], m["flag"], default=f.default, help_text=m["help"],
                         aliases=m.get("aliases", ()), metavar=_metavar(m["flag"]))


def config_from(args, agents: int, seed: int = 0) -> DQMConfig:
    """The :class:`DQMConfig` of parsed :func:`add_algorithm` options, with the command's own ``agents`` and
    ``seed`` (an agent process has no seed: the coordinator broadcasts it)."""
    return DQMConfig(agents=agents, seed=seed, **{f.name: getattr(args, f.name) for f in algorithm_fields()})


def add_tls(p, router: bool = False) -> None:
    g = p.add_argument_group("identity: mutual TLS (use tls/HOST:PORT endpoints) and/or a username")
    g.add_argument("--tls-ca", help="root CA certificate (PEM)")
    g.add_argument("--tls-cert", help="this process's certificate (PEM); its common name is its identity")
    g.add_argument("--tls-key", help="this process's private key (PEM)")
    if router:
        g.add_argument("--users", metavar="FILE",
                       help="admit only these usernames: lines of USER:PASSWORD (without TLS the traffic is not "
                            "encrypted; prefer certificates)")
    else:
        g.add_argument("--user", help="this process's username (a router started with --users)")
        g.add_argument("--password-file", metavar="FILE", help="the file holding --user's password (first line)")


def _usrpwd(args, listen: bool) -> Optional[dict]:
    """zenoh's ``transport/auth/usrpwd`` settings from --users (router) or --user/--password-file."""
    from pathlib import Path

    from ..validation import InputError

    if listen:
        users = getattr(args, "users", None)
        if not users:
            return None
        try:
            lines = [ln for ln in Path(users).read_text().splitlines() if ln.strip()]
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(f"--users {users}: cannot read it ({getattr(exc, 'strerror', None) or exc})") from None
        bad = [n for n, ln in enumerate(lines, 1) if ":" not in ln or not ln.split(":", 1)[0]]
        if not lines or bad:
            raise InputError(f"--users {users}: write one USER:PASSWORD line per user"
                             + (f" (line {bad[0]} is not)" if bad else " (the file is empty)"))
        return {"dictionary_file": str(users)}
    user, pwfile = getattr(args, "user", None), getattr(args, "password_file", None)
    if not (user or pwfile):
        return None
    if not (user and pwfile):
        raise InputError("a username needs both --user and --password-file")
    try:
        password = Path(pwfile).read_text().splitlines()[0]
    except (OSError, UnicodeDecodeError, IndexError) as exc:
        raise InputError(f"--password-file {pwfile}: cannot read a password from it "
                         f"({getattr(exc, 'strerror', None) or 'empty file'})") from None
    return {"user": user, "password": password}


def tls_from(args, listen: bool, check_files: bool = True) -> Optional[dict]:
    """zenoh's ``transport/link/tls`` settings from the ``--tls-*`` options (None without them or a
    username), plus ``usrpwd``: the ``transport/auth/usrpwd`` settings of --users or --user;
    ``check_files``: refuse a missing or non-PEM file at once (:func:`check_pem`)."""
    usrpwd = _usrpwd(args, listen)
    if not (args.tls_ca or args.tls_cert or args.tls_key):
        return {"usrpwd": usrpwd} if usrpwd else None
    from ..validation import InputError

    if not (args.tls_ca and args.tls_cert and args.tls_key):
        raise InputError("mutual TLS needs all of --tls-ca, --tls-cert and --tls-key")
    for option, path in (("--tls-ca", args.tls_ca), ("--tls-cert", args.tls_cert), ("--tls-key", args.tls_key)):
        if check_files:
            check_pem(path, option)
    side = "listen" if listen else "connect"
    tls = {"root_ca_certificate": args.tls_ca, f"{side}_certificate": args.tls_cert,
           f"{side}_private_key": args.tls_key, "enable_mtls": True}
    return {**tls, "usrpwd": usrpwd} if usrpwd else tls


def check_pem(path: str, option: str) -> None:
    """A TLS file must exist, be readable and hold PEM text: said at once, naming the option (zenoh
    would retry the connection and then blame the CA)."""
    from pathlib import Path

    from ..validation import InputError

    p = Path(path)
    if not p.exists():
        raise InputError(f"{option} {path}: no such file")
    if p.is_dir():
        raise InputError(f"{option} {path} is a folder, not a PEM file")
    try:
        head = p.read_bytes()[:1 << 16]
    except OSError as exc:
        raise InputError(f"{option} {path}: cannot read it ({exc.strerror or exc})") from None
    if b"-----BEGIN " not in head:
        raise InputError(f"{option} {path} is not a PEM file (no '-----BEGIN' line)")

