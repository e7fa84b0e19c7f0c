"""The runtime's limits as one object: timeouts, the liveliness lease, ``max_lost``, recovery, message size.

:class:`RuntimeLimits` is to the runtime what :class:`~dqm.distributed.config.DQMConfig` is to the
algorithm: every field's metadata names its command-line option, its help and the commands that take
it, so that ``dqm run``, ``dqm coordinator`` and ``dqm agent`` generate their options from it
(:func:`add_limits`, :func:`limits_from`), and a launcher hands its children the whole object as one
encoded value (``--limits=JSON``, :meth:`RuntimeLimits.to_text`) instead of rebuilding options.
Options given beside ``--limits`` override it.
"""
from __future__ import annotations

import argparse
import json
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Optional, Tuple, get_type_hints

from ..distributed.config import RECOVERY
from ..distributed.messages import MAX_MESSAGE_BYTES
from ..validation import InputError

#: the default liveliness lease (s): a process cut off from the router is declared lost after about this long
#: (a process that dies on a reachable host loses its token within milliseconds: its socket closes). 8 s, not
#: 2: on a saturated 10 Mbit/s link the router, blocked forwarding bulk data to one host, stops reading another
#: host's link for seconds, and with 2 s it took healthy processes for lost (a balanced job of 100k features on
#: 8 such hosts lost 5 processes; with 8 s it finished in 40 s, docs/distributed.md)
DEFAULT_LEASE_S = 8.0

#: how long the coordinator waits for every agent process by default (``ready_timeout_s`` None)
DEFAULT_READY_TIMEOUT_S = 30.0

#: the commands that take limits, by what they run
COORDINATOR, AGENT, RUN = "coordinator", "agent", "run"


def _meta(flag: str, help: str, commands: Tuple[str, ...], **more) -> dict:
    return {"flag": flag, "help": help, "commands": commands, **more}


@dataclass(frozen=True)
class RuntimeLimits:
    """How long a job's processes wait, when a process counts as lost and what then, how large a message
    may be. Each field's ``metadata``: its option (``flag``), ``help``, the ``commands`` that take it."""

    ready_timeout_s: Optional[float] = field(default=None, metadata=_meta(
        "--ready-timeout", "seconds the coordinator waits for every agent process to appear; missing ones count "
        "as lost (default: 30; dqm run gives many agents per core longer)", (COORDINATOR, RUN)))
    job_timeout_s: float = field(default=600.0, metadata=_meta(
        "--job-timeout", "seconds the whole job may take", (COORDINATOR, RUN), aliases=("--timeout",)))
    phase_timeout_s: float = field(default=120.0, metadata=_meta(
        "--phase-timeout", "seconds an agent process may wait in one protocol state (and take to get ready)",
        (COORDINATOR, AGENT, RUN)))
    connect_timeout_s: float = field(default=5.0, metadata=_meta(
        "--connect-timeout", "seconds of retries to reach the router", (COORDINATOR, AGENT, RUN)))
    lease_s: float = field(default=DEFAULT_LEASE_S, metadata=_meta(
        "--lease", "liveliness lease (seconds): a process cut off from the router counts as lost after about "
        "this long; a process that dies on a reachable host is seen at once (shorter: faster recovery from a "
        "lost host; too short: processes on saturated thin links are taken for lost, docs/runtime.md)",
        (COORDINATOR, AGENT, RUN)))
    max_lost: Optional[int] = field(default=None, metadata=_meta(
        "--max-lost", "agent processes the job may lose and replace (default: half of them, at least 1)",
        (COORDINATOR, RUN)))
    recovery: str = field(default=RECOVERY[0], metadata=_meta(
        "--recovery", "when an agent process is lost while the job runs: takeover (the next live process runs "
        "its agents again, the others keep their work; default) or restart (every process starts the job "
        "again)", (COORDINATOR, RUN), choices=RECOVERY))
    max_message_bytes: int = field(default=MAX_MESSAGE_BYTES, metadata=_meta(
        "--max-message-bytes", "refuse larger messages", (COORDINATOR, AGENT, RUN)))

    def validated(self) -> "RuntimeLimits":
        """Itself, or :class:`InputError` naming the option whose value is out of range."""
        for f in fields(self):
            v, flag = getattr(self, f.name), f.metadata["flag"]
            if v is None:
                continue
            if "choices" in f.metadata:
                if v not in f.metadata["choices"]:
                    raise InputError(f"{flag} must be one of {', '.join(f.metadata['choices'])}, got {v!r}")
            elif f.name == "max_lost":
                if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                    raise InputError(f"{flag} must be an integer >= 0, got {v!r}")
            elif isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0 or v != v or v == float("inf"):
                raise InputError(f"{flag} must be a positive number, got {v!r}")
        return self

    def but(self, **changes) -> "RuntimeLimits":
        return replace(self, **changes)

    @property
    def lease_ms(self) -> int:
        return max(100, int(round(self.lease_s * 1000)))

    def to_text(self) -> str:
        """The fields that differ from the defaults, as JSON: the value of ``--limits``."""
        default = RuntimeLimits()
        return json.dumps({k: v for k, v in asdict(self).items() if v != getattr(default, k)}, sort_keys=True)

    @classmethod
    def from_text(cls, text: str) -> "RuntimeLimits":
        """The inverse of :meth:`to_text`; unknown names and bad values are refused, naming them."""
        try:
            given = json.loads(text)
        except ValueError:
            raise InputError(f"--limits {text!r} is not JSON") from None
        if not isinstance(given, dict):
            raise InputError(f"--limits {text!r} is not a JSON object")
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(given) - names)
        if unknown:
            raise InputError(f"--limits names {', '.join(unknown)}, which are not limits ({', '.join(sorted(names))})")
        types = get_type_hints(cls)
        for k, v in given.items():
            if types[k] in (float, Optional[float]) and isinstance(v, int) and not isinstance(v, bool):
                given[k] = float(v)
        return cls(**given).validated()


def _type(tp):
    return {float: float, Optional[float]: float, int: int, Optional[int]: int, str: str}[tp]


def add_limits(p, command: str) -> None:
    """The options of ``command`` (:data:`COORDINATOR`, :data:`AGENT`, :data:`RUN`), one per field that names
    it, and the hidden ``--limits`` that carries the whole object from a launcher."""
    g = p.add_argument_group("runtime limits")
    types = get_type_hints(RuntimeLimits)
    for f in fields(RuntimeLimits):
        m = f.metadata
        if command not in m["commands"]:
            continue
        default = "" if f.default is None else f" (default: {f.default:g})" if isinstance(f.default, float) else ""
        help_text = m["help"] if "default:" in m["help"] else m["help"] + default
        g.add_argument(m["flag"], *m.get("aliases", ()), dest=f.name, type=_type(types[f.name]), default=None,
                       choices=m.get("choices"), help=help_text, metavar=None if "choices" in m else "N")
    g.add_argument("--limits", help=argparse.SUPPRESS)


def limits_from(args) -> RuntimeLimits:
    """The limits of parsed :func:`add_limits` options: ``--limits`` (or the defaults) with every option given
    beside it replacing its field; validated."""
    base = RuntimeLimits.from_text(args.limits) if getattr(args, "limits", None) else RuntimeLimits()
    given = {f.name: getattr(args, f.name) for f in fields(RuntimeLimits) if getattr(args, f.name, None) is not None}
    return base.but(**given).validated()


def limits_arg(limits: RuntimeLimits) -> str:
    """The one option that gives a child process ``limits``."""
    return f"--limits={limits.to_text()}"
