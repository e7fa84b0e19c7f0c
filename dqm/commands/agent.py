"""Run one Distributed QuickMatch agent: an OS process holding its own images' features.

    dqm agent --id 0 --agents 4 --connect tcp/ROUTER:7447 --job J features0.npz

FEATURES files as for `dqm match` (docs/formats.md), optionally with a
`feature_ids` array of global ids (else ids are (agent << 32) + row).
With --peer-features the process can take over a lost agent's images and cell.

Exit codes: 0 done, 2 bad input or no router, 3 job failed or aborted,
4 refused (a parameter differs from the coordinator's), 5 the coordinator was
lost, 130 interrupted, 143 terminated (SIGTERM).
"""
from ..runtime.limits import AGENT, add_limits, limits_from
from .runtime_options import add_algorithm, add_tls, config_from, tls_from

NAME = "agent"
HELP = "run one distributed agent process"
#: ``python -m dqm`` leaves with os._exit once this command returned (:data:`dqm.cli.exit_at_once`)
EXIT_AT_ONCE = True


def add_arguments(p) -> None:
    p.add_argument("--id", type=int, required=True, help="agent index 0..M-1")
    p.add_argument("--agents", type=int, required=True, help="number of agents M")
    p.add_argument("--connect", required=True, help="router endpoint, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--peer-features", action="append", metavar="AGENT=FILE[,FILE...]",
                   help="where another agent's FEATURES files can be read, so that this process can take over "
                        "that agent's images and cell if its process is lost (repeat per agent; across hosts: "
                        "shared storage)")
    p.add_argument("features", nargs="+", help="FEATURES.npz file(s) of this agent's images")
    add_algorithm(p)
    add_limits(p, AGENT)
    add_tls(p)


def run(args) -> int:
    from ..runtime.agent import main_agent, parse_peer_features
    from ..runtime.bus import AccessDenied, JobIdInUse, RouterUnreachable
    from ..validation import InputError

    if args.agents < 1:
        raise InputError(f"--agents must be at least 1, got {args.agents}")
    from ..runtime.bus import check_endpoint

    check_endpoint(args.connect)
    if not 0 <= args.id < args.agents:
        raise InputError(f"--id must be in 0..{args.agents - 1}, got {args.id}")
    cfg = config_from(args, args.agents).validated(runtime=True)
    peers = parse_peer_features(args.peer_features)
    bad = [a for a in peers if not 0 <= a < args.agents]
    if bad:
        raise InputError(f"--peer-features names agent {bad[0]}, outside 0..{args.agents - 1}")
    try:
        return main_agent(args.id, cfg, args.connect, args.features, tls_from(args, listen=False),
                          limits=limits_from(args), peers=peers)
    except (RouterUnreachable, JobIdInUse, AccessDenied) as exc:
        raise InputError(str(exc)) from None
