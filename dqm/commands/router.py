"""Run a zenoh router (Python; no zenohd needed) until Ctrl-C / SIGTERM.

    dqm router --listen tcp/127.0.0.1:7447
    dqm router --listen tls/0.0.0.0:7448 --tls-ca ca.pem --tls-cert router.pem --tls-key router.key
"""
from .runtime_options import add_tls, tls_from

NAME = "router"
HELP = "run a zenoh router for dqm agents"


def add_arguments(p) -> None:
    p.add_argument("--listen", action="append", required=True, help="endpoint(s) to listen on, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--ready-file", help="write this file once listening")
    add_tls(p)


def run(args) -> int:
    from ..runtime.bus import check_endpoint
    from ..runtime.router import main_router

    for endpoint in args.listen:
        check_endpoint(endpoint, "--listen")
    return main_router(args.listen, tls_from(args, listen=True), args.ready_file)
