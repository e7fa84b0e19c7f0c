"""A zenoh router from Python (no zenohd binary is needed): routing runs in
zenoh's own threads; this process only holds the session open until SIGTERM /
Ctrl-C, then closes it cleanly.

With a roster (``dqm router --acl ROSTER``, :mod:`dqm.runtime.roster`) the router
enforces default-deny access control, and reports every admitted client whose
identity is not in the roster (zenoh itself logs only its session id): such a
client can do nothing, which otherwise shows up only as a job that never starts.
"""
from __future__ import annotations

import json
import signal
import sys
import threading
from typing import Dict, List, Optional

from .. import signals
from .bus import router_config, zenoh_message
from .roster import Roster, access_control


def _say(text: str) -> None:
    print(f"[router] {text}", file=sys.stderr, flush=True)


class IdentityWatch:
    """Polls the router's admin space for its clients' links and the identity each authenticated with
    (``auth_identifier``: the client certificate's common name); reports, once per link, the identities
    the roster does not know. zenoh does not show a link's username there, so a router that identifies
    clients by username only (``certificates=False``) cannot tell who they are and reports nothing."""

    def __init__(self, session, roster: Roster, certificates: bool = True):
        self.session = session
        self.roster = roster
        self.certificates = certificates
        self.known = roster.names()
        self.seen: Dict[str, str] = {}  # link key -> identity

    def poll(self) -> None:
        zid = str(self.session.zid())
        try:
            replies = list(self.session.get(f"@/{zid}/session/transport/unicast/*/link/*", timeout=1.0))
        except Exception:  # noqa: BLE001 - the router is closing
            return
        for r in replies:
            if r.ok is None:
                continue
            link = str(r.ok.key_expr)
            if link in self.seen:
                continue
            try:
                info = json.loads(r.ok.payload.to_bytes())
            except ValueError:
                continue
            who = str(info.get("auth_identifier") or "")
            self.seen[link] = who
            if who not in self.known and self.certificates:
                what = f"identity {who!r}" if who else "a client without an identity (no certificate, no username)"
                _say(f"{what} from {info.get('dst', '?')} is not in the roster {self.roster.source}: the router "
                     "lets it do nothing (add a line for it, or check which certificate it uses)")


def main_router(endpoints: List[str], tls: Optional[dict] = None, ready_file: Optional[str] = None,
                roster: Optional[Roster] = None) -> int:
    """Entry point of ``dqm router``; ``roster``: enforce its access control over the identities
    ``tls`` authenticates (certificate common names; usernames when it holds ``usrpwd``)."""
    import zenoh

    from .lifeline import watch_parent

    stop = threading.Event()
    came: list = []

    def _stop(signum, frame):
        came.append(signum)
        stop.set()

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    watch_parent()
    # identities are certificate common names (TLS settings beside ``usrpwd``) and/or usernames
    kinds = (["cert"] if set(tls or {}) - {"usrpwd"} else []) + (["user"] if (tls or {}).get("usrpwd") else [])
    acl = access_control(roster, subjects=kinds) if roster is not None else None
    try:
        session = zenoh.open(router_config(endpoints, tls, acl))
    except Exception as exc:  # noqa: BLE001 - port in use, bad address, bad certificate
        _say(f"error: cannot listen on {', '.join(endpoints)}: {zenoh_message(exc)}")
        return 2
    try:
        _say(f"listening on {', '.join(endpoints)}")
        watch = None
        if roster is not None:
            watch = IdentityWatch(session, roster, certificates="cert" in kinds)
            _say(f"access control: {len(roster.identities)} identities from {roster.source}, everything else "
                 f"denied{'; jobs ' + ', '.join(roster.jobs) if roster.jobs else ''}")
        if ready_file:
            with open(ready_file, "w") as fh:
                fh.write("ready\n")
        while not stop.wait(0.5):
            if watch is not None:
                watch.poll()
        # stopped as every command is: 130 after Ctrl-C, 143 after SIGTERM (dqm.signals), one line
        terminated = came[0] == signal.SIGTERM
        _say("terminated" if terminated else "interrupted")
        return signals.EXIT_TERMINATED if terminated else signals.EXIT_INTERRUPTED
    finally:
        session.close()
