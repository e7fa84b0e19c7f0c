"""Run a zenoh router (Python; no zenohd needed) until Ctrl-C / SIGTERM.

    dqm router --listen tcp/127.0.0.1:7447
    dqm router --listen tls/0.0.0.0:7448 --tls-ca ca.pem --tls-cert router.pem --tls-key router.key
    dqm router --listen tls/0.0.0.0:7448 --tls-ca ca.pem --tls-cert router.pem --tls-key router.key --acl roster.txt

With --acl ROSTER (dqm.runtime.roster; needs identities: mutual TLS and/or --users) every
identity may use only its own keys, everything else is denied, and the router reports
clients whose identity the roster does not list.
"""
from .runtime_options import add_tls, tls_from

NAME = "router"
HELP = "run a zenoh router for dqm agents"


def add_arguments(p) -> None:
    p.add_argument("--listen", action="append", required=True, help="endpoint(s) to listen on, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--ready-file", help="write this file once listening")
    p.add_argument("--acl", metavar="ROSTER",
                   help="enforce access control: each identity in ROSTER (lines 'ROLE IDENTITY [INDEX]', roles "
                        "coordinator, agent, stream, camera, viewer) may use only its own keys; all else is denied")
    add_tls(p, router=True)


def run(args) -> int:
    from ..runtime.bus import check_endpoint
    from ..runtime.roster import load_roster
    from ..runtime.router import main_router
    from ..validation import InputError

    for endpoint in args.listen:
        check_endpoint(endpoint, "--listen")
    tls = tls_from(args, listen=True)
    roster = load_roster(args.acl) if args.acl else None
    if roster is not None and not tls:
        raise InputError("--acl needs identities: give the router --tls-ca/--tls-cert/--tls-key (mutual TLS: "
                         "identities are certificate common names) and/or --users")
    return main_router(args.listen, tls, args.ready_file, roster)
