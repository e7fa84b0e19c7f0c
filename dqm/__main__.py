import os
import sys

try:
    from .cli import program
except KeyboardInterrupt:  # Ctrl-C before dqm could own it: still its exit code, no traceback
    print("dqm: interrupted", file=sys.stderr)
    sys.stderr.flush()
    os._exit(130)

program()
