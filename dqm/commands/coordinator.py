"""Run the coordinator of a distributed job: waits for all agents, broadcasts the
partition seed integer, collects results, writes the report (JSON).

    dqm coordinator --agents 4 --seed 1 --connect tcp/ROUTER:7447 --job J --out report.json
"""
from .runtime_options import add_tls, tls_from
from ..distributed.partition import PARTITION_MODES

NAME = "coordinator"
HELP = "run the coordinator of a distributed job"


def add_arguments(p) -> None:
    p.add_argument("--agents", type=int, required=True)
    p.add_argument("--seed", type=int, default=0, help="the partition seed integer (the only thing broadcast)")
    p.add_argument("--partition", choices=PARTITION_MODES, default="kmeans")
    p.add_argument("--connect", required=True)
    p.add_argument("--job", default="job")
    p.add_argument("--out", help="report JSON (labels, traffic per link and kind)")
    p.add_argument("--tcp-port", type=int, help="router port: also record kernel TCP byte counters")
    p.add_argument("--ready-timeout", type=float, default=30.0)
    p.add_argument("--job-timeout", type=float, default=600.0)
    p.add_argument("--connect-timeout", type=float, default=5.0)
    add_tls(p)


def run(args) -> int:
    from ..distributed.partition import check_agents, check_seed
    from ..runtime.bus import RouterUnreachable
    from ..runtime.coordinator import main_coordinator
    from ..validation import InputError

    check_agents(args.agents)
    check_seed(args.seed)
    try:
        return main_coordinator(args.agents, args.seed, args.partition, args.connect, args.job, args.out,
                                tls_from(args, listen=False), args.tcp_port, args.ready_timeout,
                                args.job_timeout, args.connect_timeout)
    except RouterUnreachable as exc:
        raise InputError(str(exc)) from None
