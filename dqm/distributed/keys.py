"""The key space of a dqm job (documented in docs/runtime.md): where every message goes.

The runtime puts on these zenoh keys; the simulator meters their length too.

Everything of one job lives under ``dqm/<job>/``, so concurrent jobs on one
router never see each other's traffic:

* ``dqm/<job>/agent/<i>``        messages to agent i (any sender)
* ``dqm/<job>/coordinator``      messages to the coordinator
* ``dqm/<job>/alive/agent/<i>``  liveliness token of agent i
* ``dqm/<job>/alive/coordinator`` liveliness token of the coordinator

Streaming (``dqm stream``, :mod:`dqm.runtime.stream`):

* ``dqm/<job>/stream/images``   camera nodes put ``image`` messages here (one image each)
* ``dqm/<job>/stream/changes``  the stream publishes one ``changes`` message per add or remove
* ``dqm/<job>/alive/stream``    liveliness token of the stream: declared once it subscribes, so
  a camera node waits for it before its first put (a put before is lost)
"""
import re

from ..validation import InputError

_JOB = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")


def check_job(job: str) -> str:
    if not isinstance(job, str) or not _JOB.match(job):
        raise InputError(f"job id must be 1-64 characters of letters, digits, '_', '.', '-'; got {job!r}")
    return job


def agent_inbox(job: str, i: int) -> str:
    return f"dqm/{job}/agent/{int(i)}"


def coordinator_inbox(job: str) -> str:
    return f"dqm/{job}/coordinator"


def alive_agent(job: str, i: int) -> str:
    return f"dqm/{job}/alive/agent/{int(i)}"


def alive_coordinator(job: str) -> str:
    return f"dqm/{job}/alive/coordinator"


def alive_all(job: str) -> str:
    return f"dqm/{job}/alive/**"


def stream_images(job: str) -> str:
    return f"dqm/{job}/stream/images"


def stream_changes(job: str) -> str:
    return f"dqm/{job}/stream/changes"


def alive_stream(job: str) -> str:
    return f"dqm/{job}/alive/stream"
