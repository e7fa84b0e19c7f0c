"""A zenoh router from Python (no zenohd binary is needed): routing runs in
zenoh's own threads; this process only holds the session open until SIGTERM /
Ctrl-C, then closes it cleanly."""
from __future__ import annotations

import signal
import sys
import threading
from typing import List, Optional

from .bus import router_config, zenoh_message


def main_router(endpoints: List[str], tls: Optional[dict] = None, ready_file: Optional[str] = None) -> int:
    import zenoh

    from .lifeline import watch_parent

    stop = threading.Event()

    def _stop(signum, frame):
        stop.set()

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    watch_parent()
    try:
        session = zenoh.open(router_config(endpoints, tls))
    except Exception as exc:  # noqa: BLE001 - port in use, bad address, bad certificate
        print(f"[router] error: cannot listen on {', '.join(endpoints)}: {zenoh_message(exc)}", file=sys.stderr,
              flush=True)
        return 2
    try:
        print(f"[router] listening on {', '.join(endpoints)}", file=sys.stderr, flush=True)
        if ready_file:
            with open(ready_file, "w") as fh:
                fh.write("ready\n")
        while not stop.wait(0.2):
            pass
        return 0
    finally:
        session.close()
