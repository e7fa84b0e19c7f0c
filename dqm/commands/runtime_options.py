"""Options shared by the runtime commands (algorithm parameters, TLS)."""
from __future__ import annotations

from typing import Optional

from ..core.clustering import DEFAULT_RHO, KERNELS
from ..distributed.config import DEFAULT_MODE, DEFAULT_SKETCH_DIMS, GHOST_RULES, MODES, DQMConfig
from ..distributed.partition import PARTITION_MODES


def add_algorithm(p) -> None:
    g = p.add_argument_group("algorithm (must be the same for every agent of a job)")
    g.add_argument("--mode", choices=MODES, default=DEFAULT_MODE,
                   help="balanced (clusters identical to centralized, work spread evenly), lean (the hand-down "
                        "cascade: fewer bytes, work gathers at agent 0) or paper (the seed paper's literal "
                        "procedure); docs/distributed.md")
    g.add_argument("--partition", choices=PARTITION_MODES, default="kmeans",
                   help="how the cell seeds are drawn from the seed integer")
    g.add_argument("--rho", type=float, default=DEFAULT_RHO, help="merge ratio")
    g.add_argument("--kernel", choices=KERNELS, default="quadratic",
                   help="density kernel. Quadratic here (finite support, so a density never needs features "
                        "beyond a cell's halo), while dqm match and dqm demo default to the reference code's "
                        "Gaussian; with the same kernel the clusters equal dqm.quickmatch's")
    g.add_argument("--halo", type=float, default=1.0, help="lean/paper: contested-test width factor (1 = safe)")
    g.add_argument("--samples", type=int, default=64, help="set-up sample descriptors per agent")
    g.add_argument("--seed-norm", type=float, default=512.0, help="descriptor norm for seeded seeds (SIFT: 512)")
    g.add_argument("--cell-weights", dest="cell_weights", action="store_true", default=None,
                   help="balance the cells with power-diagram weights (default: on in balanced mode)")
    g.add_argument("--no-cell-weights", dest="cell_weights", action="store_false", default=None,
                   help="plain Voronoi cells")
    g.add_argument("--ghost-rule", choices=GHOST_RULES, default="one-way",
                   help="balanced: one-way (default) or two-way (the plain bisector halo, for comparison)")
    g.add_argument("--sketch-dims", type=int, default=DEFAULT_SKETCH_DIMS,
                   help="balanced: dimension of the lower-bound sketch pre-filter (0 = off)")
    g.add_argument("--balance-rounds", type=int, default=12, help="most rounds of cell-weight refinement")
    g.add_argument("--job", default="job", help="job id; keeps concurrent jobs on one router apart")


def config_from(args, agents: int, seed: int = 0) -> DQMConfig:
    return DQMConfig(agents=agents, seed=seed, partition=args.partition, mode=args.mode, rho=args.rho,
                     kernel=args.kernel, samples_per_agent=args.samples, halo=args.halo,
                     seed_norm=args.seed_norm, job=args.job, cell_weights=args.cell_weights,
                     ghost_rule=args.ghost_rule, sketch_dims=args.sketch_dims, balance_rounds=args.balance_rounds)


def add_tls(p) -> None:
    g = p.add_argument_group("mutual TLS (use tls/HOST:PORT endpoints)")
    g.add_argument("--tls-ca", help="root CA certificate (PEM)")
    g.add_argument("--tls-cert", help="this process's certificate (PEM)")
    g.add_argument("--tls-key", help="this process's private key (PEM)")


def tls_from(args, listen: bool, check_files: bool = True) -> Optional[dict]:
    """zenoh's ``transport/link/tls`` settings from the ``--tls-*`` options (None without them);
    ``check_files``: refuse a missing or non-PEM file at once (:func:`check_pem`)."""
    if not (args.tls_ca or args.tls_cert or args.tls_key):
        return None
    from ..validation import InputError

    if not (args.tls_ca and args.tls_cert and args.tls_key):
        raise InputError("mutual TLS needs all of --tls-ca, --tls-cert and --tls-key")
    for option, path in (("--tls-ca", args.tls_ca), ("--tls-cert", args.tls_cert), ("--tls-key", args.tls_key)):
        if check_files:
            check_pem(path, option)
    side = "listen" if listen else "connect"
    return {"root_ca_certificate": args.tls_ca, f"{side}_certificate": args.tls_cert,
            f"{side}_private_key": args.tls_key, "enable_mtls": True}


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
