import os
import sys


def _leave(code: int, text: str = "") -> None:
    """End at once with ``code``: nothing has started yet (see :data:`dqm.cli.interrupted_while_importing`)."""
    if text:
        print(text, file=sys.stderr)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


try:
    from . import cli
except KeyboardInterrupt:  # Ctrl-C before dqm could own it: still its exit code, no traceback
    _leave(130, "dqm: interrupted")

code = cli.main()
if cli.interrupted_while_importing:
    _leave(code)
sys.exit(code)
