"""Run the coordinator of a distributed job: waits for all agents, broadcasts the
partition seed integer (and the parameters every agent checks), collects
results, replaces lost agent processes, writes the report (JSON).

    dqm coordinator --agents 4 --seed 1 --connect tcp/ROUTER:7447 --job J --out report.json

Give it the same algorithm options as the agents: an agent started with a
different value refuses, and the coordinator names the parameter.

Exit codes: 0 done, 2 bad input or no router, 3 job failed (see the paragraph
it prints and REPORT.failure.json), 4 an agent refused the job, 130
interrupted, 143 terminated (SIGTERM).
"""
import argparse

from .. import outputs
from ..distributed.config import DEFAULT_SEED
from ..runtime.limits import COORDINATOR, add_limits, limits_from
from .runtime_options import add_algorithm, add_tls, config_from, tls_from

NAME = "coordinator"
HELP = "run the coordinator of a distributed job"
#: ``python -m dqm`` leaves with os._exit once this command returned (:data:`dqm.cli.exit_at_once`)
EXIT_AT_ONCE = True


def add_arguments(p) -> None:
    p.add_argument("--agents", type=int, required=True, help="number of agents M")
    p.add_argument("--seed", type=int, default=DEFAULT_SEED,
                   help="the partition seed integer (the only thing broadcast)")
    p.add_argument("--connect", required=True, help="router endpoint, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--out", help="report JSON (labels, traffic per link and kind); on failure OUT.failure.json")
    p.add_argument("--clusters", metavar="CLUSTERS.npz",
                   help="the job's CLUSTERS file: labels with the keypoints, image names and ground truth the "
                        "agents' FEATURES carry, for dqm plot / export / evaluate (docs/formats.md; default: "
                        "./dqm-out/coordinator/JOB.npz)")
    p.add_argument("--no-clusters", action="store_true",
                   help="write no CLUSTERS file (the agents then send no catalogs: fewer bytes)")
    outputs.add_overwrite_option(p)
    p.add_argument("--tcp-port", type=int, help="router port: also record kernel TCP byte counters")
    p.add_argument("--host-cores", type=float, metavar="CORES",
                   help="--mode auto: the cores of each agent host, for the cost model that picks the mode "
                        "(default: this host's, its CPU quota included)")
    p.add_argument("--gather-cores", type=float, metavar="CORES",
                   help="--mode auto: the cores agent 0's host gives a gather, once the other agents have sent "
                        "their features (default: this host's, its CPU quota included)")
    p.add_argument("--also-agent", metavar="'AGENT OPTIONS'",
                   help="also run `dqm agent AGENT OPTIONS` (one shell-quoted string) on this host, in a process "
                        "forked from this one once its imports are done: the coordinator's host starts one "
                        "Python interpreter instead of two (docs/runtime.md, Start-up)")
    p.add_argument("--also-agent-log", metavar="PATH",
                   help="where the --also-agent process writes its output (default: where this one does)")
    p.add_argument("--progress-fd", type=int, help=argparse.SUPPRESS)
    add_limits(p, COORDINATOR)
    add_algorithm(p)
    add_tls(p)


def run(args) -> int:
    from ..distributed import keys
    from ..distributed.partition import check_agents, check_seed
    from ..runtime.bus import AccessDenied, JobIdInUse, RouterUnreachable, check_endpoint
    from ..runtime.coordinator import main_coordinator
    from ..validation import InputError

    check_agents(args.agents)
    check_seed(args.seed)
    check_endpoint(args.connect)
    keys.check_job(args.job)
    if args.out:
        outputs.check_file(args.out, "--out", (".json",), overwrite=args.overwrite)
    if args.clusters and args.no_clusters:
        raise InputError("--clusters and --no-clusters contradict each other; give one")
    clusters = None if args.no_clusters else str(outputs.check_file(
        args.clusters or outputs.default_dir("coordinator") / f"{args.job}.npz", "--clusters", (".npz",),
        overwrite=args.overwrite, default=not args.clusters))
    limits = limits_from(args)
    for option, value in (("--host-cores", args.host_cores), ("--gather-cores", args.gather_cores)):
        if value is not None and not value > 0:
            raise InputError(f"{option} must be positive, got {value}")
    cfg = config_from(args, args.agents, args.seed).validated(runtime=True)
    agent = also_agent(args.also_agent, args.also_agent_log, args._main, args._parse)
    try:
        return main_coordinator(cfg, args.connect, args.out, tls_from(args, listen=False), args.tcp_port, limits,
                                args.progress_fd, clusters, args.host_cores, args.gather_cores)
    except (RouterUnreachable, JobIdInUse, AccessDenied) as exc:
        raise InputError(str(exc)) from None
    finally:
        if agent is not None:
            import logging

            from ..runtime.lifeline import reap

            code = reap(agent, AGENT_EXIT_WAIT_S)
            if code:
                logging.getLogger("dqm.runtime").warning("the --also-agent process exited with code %d", code)


#: how long the coordinator waits for its --also-agent process to exit (it has left the job by then)
AGENT_EXIT_WAIT_S = 2.0


def also_agent(options, log_path, main, parse):
    """Start ``dqm agent OPTIONS`` forked from this process (--also-agent): its options checked here first with
    ``parse(argv, option)`` (dqm.cli.parse_command: a bad one is this command's error, before any work), the
    agent's modules imported here, so that the child starts with them, and the child running ``main(argv)``
    (dqm.cli.main). Returns its pid, or None without --also-agent."""
    if not options:
        return None
    import shlex

    from ..runtime import agent  # noqa: F401 - imported once, before the fork
    from ..runtime.lifeline import fork_call
    from ..validation import InputError

    try:
        argv = ["agent", *shlex.split(options)]
    except ValueError as exc:
        raise InputError(f"--also-agent: {exc}") from None
    parse(argv, "--also-agent")
    if log_path:
        outputs.check_file(log_path, "--also-agent-log", overwrite=True)
    return fork_call(lambda: main(argv), log_path)
