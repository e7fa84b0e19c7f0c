"""Who may do what on a dqm router: the roster and the access-control rules built from it.

A roster is a text file the operator writes once, one identity per line::

    # ROLE         IDENTITY        [INDEX]
    coordinator    coordinator
    agent          agent0          0        # agent process 0
    agent          agent1          1
    stream         stream
    camera         cam-north       0        # camera node 0 (dqm camera --camera 0)
    viewer         dashboard                # may read the stream's change sets
    job            survey-7                 # optional, repeatable: only these job ids (default: any)

An identity is a certificate's common name (mutual TLS: the CN that
``deploy/make-certs.sh NAME`` writes) or a username (``--users``). ``dqm router
--acl ROSTER`` turns the roster into zenoh's ``access_control`` block
(:func:`access_control`) with **default deny**: every identity may put only on
keys that name itself as the sender, subscribe only to its own inbox and declare
only its own liveliness token (the key space: :mod:`dqm.distributed.keys`). An
admitted client that is in no line can do nothing.

Each identity is on one line only (a robot's agent and its camera node hold two
certificates); an agent or camera index belongs to one identity.
"""
from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

from ..distributed import keys
from ..validation import InputError

LOG = logging.getLogger("dqm.runtime")

#: roles an identity may hold; agent and camera take an index
ROLES = ("coordinator", "agent", "stream", "camera", "viewer")
INDEXED = ("agent", "camera")
#: how identities are authenticated: certificate common names (mutual TLS), usernames (user/password)
SUBJECT_KINDS = {"cert": "cert_common_names", "user": "usernames"}

_NAME = re.compile(r"^[A-Za-z0-9_.@:=+-]{1,128}$")
_INDEX = re.compile(r"^(0|[1-9][0-9]{0,8})$")


class RosterError(InputError):
    """A roster that cannot be used; the text names the file and the line."""


@dataclass(frozen=True)
class Identity:
    """One roster line: ``name`` holds ``role`` (with ``index`` for agent processes and camera nodes)."""

    role: str
    name: str
    index: Optional[int] = None
    line: int = field(default=0, compare=False)  # where the roster says it

    def describe(self) -> str:
        return f"{self.role} {self.index}" if self.index is not None else self.role

    def as_line(self) -> str:
        return " ".join([self.role, self.name] + ([str(self.index)] if self.index is not None else []))


@dataclass(frozen=True)
class Roster:
    identities: Tuple[Identity, ...]
    jobs: Tuple[str, ...] = ()  # empty: any job
    source: str = field(default="roster", compare=False)

    def names(self) -> Dict[str, Identity]:
        return {i.name: i for i in self.identities}

    def text(self) -> str:
        lines = [i.as_line() for i in self.identities] + [f"job {j}" for j in self.jobs]
        return "\n".join(lines) + "\n"


def parse_roster(text: str, source: str = "roster") -> Roster:
    """A :class:`Roster` from its text; :class:`RosterError` names ``source`` and the line of the first problem."""
    identities: List[Identity] = []
    jobs: List[str] = []
    seen: Dict[str, int] = {}
    indices: Dict[Tuple[str, int], int] = {}
    for n, raw in enumerate(text.splitlines(), 1):
        words = raw.split("#", 1)[0].split()
        if not words:
            continue
        where = f"{source}, line {n}"
        role = words[0]
        if role == "job":
            if len(words) != 2:
                raise RosterError(f"{where}: write 'job JOB_ID', got {raw.strip()!r}")
            try:
                jobs.append(keys.check_job(words[1]))
            except InputError as exc:
                raise RosterError(f"{where}: {exc}") from None
            continue
        if role not in ROLES:
            raise RosterError(f"{where}: unknown role {role!r}; the roles are {', '.join(ROLES)} (and 'job')")
        want = 3 if role in INDEXED else 2
        if len(words) != want:
            form = f"{role} IDENTITY INDEX" if role in INDEXED else f"{role} IDENTITY"
            raise RosterError(f"{where}: write '{form}', got {raw.strip()!r}")
        name = words[1]
        if not _NAME.match(name):
            raise RosterError(f"{where}: identity {name!r} must be 1-128 letters, digits or _ . @ : = + -")
        if name in seen:
            raise RosterError(f"{where}: identity {name!r} is listed twice (first on line {seen[name]}); give each "
                              "role its own certificate or username")
        seen[name] = n
        index = None
        if role in INDEXED:
            if not _INDEX.match(words[2]):
                raise RosterError(f"{where}: {role} index {words[2]!r} must be a non-negative integer")
            index = int(words[2])
            if (role, index) in indices:
                raise RosterError(f"{where}: {role} {index} is given to two identities (also on line "
                                  f"{indices[(role, index)]})")
            indices[(role, index)] = n
        identities.append(Identity(role, name, index, n))
    if not identities:
        raise RosterError(f"{source}: no identities (write one 'ROLE IDENTITY [INDEX]' line per identity)")
    return Roster(tuple(identities), tuple(dict.fromkeys(jobs)), source)


def load_roster(path: str) -> Roster:
    """Read and parse a roster file; one :class:`RosterError` line on any problem."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise RosterError(f"cannot read the roster {path}: {exc.strerror or exc}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise RosterError(f"the roster {path} is not UTF-8 text") from None
    roster = parse_roster(text, str(path))
    LOG.info("roster %s: %d identities, jobs %s", path, len(roster.identities), ", ".join(roster.jobs) or "any")
    return roster


def job_roster(agents: int, jobs: Sequence[str] = ()) -> Roster:
    """The roster of one job's processes as ``dqm run --secure`` names them: coordinator, agent0..."""
    ids = [Identity("coordinator", "coordinator")] + [Identity("agent", f"agent{p}", p) for p in range(agents)]
    return Roster(tuple(ids), tuple(jobs), "dqm run --secure")


def _rules_of(identity: Identity, job: str) -> List[Tuple[str, str, Sequence[str]]]:
    """(flow, messages, key expressions) the identity is allowed, for one job pattern."""
    root = f"dqm/{job}"
    alive = [("ingress", "declare_liveliness_subscriber liveliness_query", [f"{root}/alive/**"]),
             ("egress", "liveliness_token reply", [f"{root}/alive/**"])]

    def process(p: int, token: str):
        me = keys.process_name(p)
        return [("ingress", "put", [f"{root}/proc/*/from/{me}/**"]),
                ("egress", "declare_subscriber", [f"{root}/proc/*/from/{me}/**"]),
                ("ingress", "declare_subscriber", [f"{root}/proc/{me}/**"]),
                ("egress", "put", [f"{root}/proc/{me}/**"]),
                ("ingress", "liveliness_token", [token])]

    if identity.role == "coordinator":
        return alive + process(-1, keys.alive_coordinator(job))
    if identity.role == "agent":
        return alive + process(identity.index, keys.alive_agent(job, identity.index))
    if identity.role == "stream":
        return alive + [("ingress", "declare_subscriber", [f"{root}/stream/images/**"]),
                        ("egress", "put", [f"{root}/stream/images/**"]),
                        ("ingress", "put", [keys.stream_changes(job)]),
                        ("egress", "declare_subscriber", [keys.stream_changes(job)]),
                        ("ingress", "liveliness_token", [keys.alive_stream(job)])]
    if identity.role == "camera":
        own, probe = keys.camera_images(job, identity.index), keys.camera_probe(job, identity.index)
        return alive + [("ingress", "put", [own]), ("egress", "declare_subscriber", [own]),
                        ("ingress", "put declare_subscriber", [probe]), ("egress", "put declare_subscriber", [probe])]
    if identity.role == "viewer":
        return alive + [("ingress", "declare_subscriber", [keys.stream_changes(job)]),
                        ("egress", "put", [keys.stream_changes(job)])]
    raise AssertionError(identity.role)


def access_control(roster: Roster, subjects: Sequence[str] = ("cert",)) -> dict:
    """zenoh's ``access_control`` configuration for ``roster``: default deny, and for every identity
    exactly its own keys. ``subjects``: how the router authenticates identities (:data:`SUBJECT_KINDS`)."""
    for s in subjects:
        if s not in SUBJECT_KINDS:
            raise ValueError(f"unknown subject kind {s!r}")
    rules, subj, policies = [], [], []
    jobs = roster.jobs or ("*",)
    for k, identity in enumerate(roster.identities):
        ids = []
        for job in jobs:
            for flow, msgs, exprs in _rules_of(identity, job):
                rid = f"r{k}-{len(ids)}"
                ids.append(rid)
                rules.append({"id": rid, "permission": "allow", "flows": [flow], "messages": msgs.split(),
                              "key_exprs": list(exprs)})
        sids = []
        for kind in subjects:
            sid = f"s{k}-{kind}"
            sids.append(sid)
            subj.append({"id": sid, SUBJECT_KINDS[kind]: [identity.name]})
        policies.append({"id": f"p{k}", "rules": ids, "subjects": sids})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subj, "policies": policies}
