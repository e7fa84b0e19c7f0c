"""The key space of a dqm job (documented in docs/runtime.md): where every message goes.

The runtime puts on these zenoh keys; the simulator meters their length too.

Everything of one job lives under ``dqm/<job>/``, so concurrent jobs on one
router never see each other's traffic. Every key names its sender, and inboxes
belong to processes, not to agents, so that a router's access control
(``dqm router --acl ROSTER``, :mod:`dqm.runtime.roster`) can give each identity
exactly its own keys: it may put only on keys that name itself as the sender and
subscribe only to its own inbox. A process that takes over a lost agent's cell
keeps its own inbox; senders address the agent's new process.

* ``dqm/<job>/proc/<P>/from/<Q>/to/<a>``  a message from process Q to agent a, hosted by process P
* ``dqm/<job>/proc/coordinator/from/<Q>`` a message from process Q to the coordinator
* ``dqm/<job>/proc/<P>/from/coordinator/to/<a>`` a message from the coordinator (P, Q: process
  indices; agent process p starts out hosting agent p)
* ``dqm/<job>/proc/<P>/from/<P>/probe``   a process's check that the router lets it use its keys
* ``dqm/<job>/alive/agent/<p>``  liveliness token of agent process p
* ``dqm/<job>/alive/coordinator`` liveliness token of the coordinator

Gathering (:mod:`dqm.runtime.gather`: every source's features to one host, the centralized baseline):

* ``dqm/<job>/gather/from/<Q>``  source Q's features, in parts
* ``dqm/<job>/alive/gather``     liveliness token of the gathering host, declared once it subscribes

Streaming (``dqm stream``, :mod:`dqm.runtime.stream`):

* ``dqm/<job>/stream/images/from/<c>``  camera node c puts ``image`` messages here (one image each)
* ``dqm/<job>/stream/images/from/<c>/probe``  camera node c's check that the router lets it put as
  camera c (the stream's subscription ``from/*`` does not reach it)
* ``dqm/<job>/stream/changes``  the stream publishes one ``changes`` message per add or remove
* ``dqm/<job>/alive/stream``    liveliness token of the stream: declared once it subscribes, so
  a camera node waits for it before its first put (a put before is lost)
"""
import re

from ..validation import InputError

_JOB_ID = r"[A-Za-z0-9_.-]{1,64}"
_JOB = re.compile(rf"^{_JOB_ID}$")


def check_job(job: str) -> str:
    if not isinstance(job, str) or not _JOB.match(job):
        raise InputError(f"job id must be 1-64 characters of letters, digits, '_', '.', '-'; got {job!r}")
    return job


#: the coordinator's name in keys (processes are named by their index)
COORDINATOR = "coordinator"
_PROCESS = r"(coordinator|0|[1-9][0-9]{0,8})"
_MESSAGE_KEY = re.compile(rf"^dqm/({_JOB_ID})/proc/{_PROCESS}/from/{_PROCESS}"
                          r"(?:/to/(0|[1-9][0-9]{0,8}))?$")
#: keys of sources that put into one space: camera nodes (``stream/images``), gathered sources (``gather``)
_SOURCE_KEY = re.compile(rf"^dqm/({_JOB_ID})/(stream/images|gather)/from/(0|[1-9][0-9]{{0,9}})$")


def process_name(p: int) -> str:
    """A process in keys: its index, or ``coordinator`` (-1)."""
    return COORDINATOR if int(p) < 0 else str(int(p))


def message_key(job: str, src_process: int, dst_process: int, dst_agent: int) -> str:
    """The key of a message from process ``src_process`` to agent ``dst_agent`` hosted by
    ``dst_process`` (-1 for the coordinator, as process or as destination)."""
    key = f"dqm/{job}/proc/{process_name(dst_process)}/from/{process_name(src_process)}"
    return key if dst_process < 0 else f"{key}/to/{int(dst_agent)}"


def process_inbox(job: str, p: int) -> str:
    """What process ``p`` (-1: the coordinator) subscribes to: every message to it, from anyone."""
    return f"dqm/{job}/proc/{process_name(p)}/from/*/**"


def probe_key(job: str, p: int) -> str:
    """Where process ``p`` checks, through the router, that it may use its keys."""
    return f"dqm/{job}/proc/{process_name(p)}/from/{process_name(p)}/probe"


def parse_message_key(job: str, key: str):
    """``(src_process, dst_process, dst_agent)`` of a message key of ``job`` (-1: the coordinator;
    ``dst_agent`` is -1 for the coordinator); None when ``key`` is not one."""
    m = _MESSAGE_KEY.match(str(key))
    if m is None or m.group(1) != job:
        return None
    dst, src, agent = m.group(2), m.group(3), m.group(4)
    dst_p = -1 if dst == COORDINATOR else int(dst)
    if (dst_p < 0) != (agent is None):
        return None  # the coordinator's inbox has no agent; an agent process's inbox names one
    return (-1 if src == COORDINATOR else int(src)), dst_p, (-1 if agent is None else int(agent))


def alive_agent(job: str, i: int) -> str:
    return f"dqm/{job}/alive/agent/{int(i)}"


def alive_coordinator(job: str) -> str:
    return f"dqm/{job}/alive/coordinator"


def alive_all(job: str) -> str:
    return f"dqm/{job}/alive/**"


def stream_images(job: str) -> str:
    """What the stream subscribes to: every camera node's images."""
    return f"dqm/{job}/stream/images/from/*"


def camera_images(job: str, camera: int) -> str:
    """Where camera node ``camera`` puts its images."""
    return f"dqm/{job}/stream/images/from/{int(camera)}"


def camera_probe(job: str, camera: int) -> str:
    """Where camera node ``camera`` checks at start-up that the router lets it put as camera ``camera``."""
    return f"{camera_images(job, camera)}/probe"


def _source_of_key(job: str, space: str, key: str):
    """The source a ``dqm/<job>/<space>/from/<source>`` key names, or None when it is not one."""
    m = _SOURCE_KEY.match(str(key))
    return int(m.group(3)) if m and m.group(1) == job and m.group(2) == space else None


def camera_of_key(job: str, key: str):
    """The camera id a stream image key names, or None when it is not one of ``job``'s."""
    return _source_of_key(job, "stream/images", key)


def stream_changes(job: str) -> str:
    return f"dqm/{job}/stream/changes"


def alive_stream(job: str) -> str:
    return f"dqm/{job}/alive/stream"


def gather_from(job: str, src: int) -> str:
    """Where source ``src`` puts its features for the gathering host."""
    return f"dqm/{job}/gather/from/{int(src)}"


def gather_inbox(job: str) -> str:
    return f"dqm/{job}/gather/from/*"


def gather_source_of_key(job: str, key: str):
    """The source a gather key names, or None when it is not one of ``job``'s."""
    return _source_of_key(job, "gather", key)


def alive_gather(job: str) -> str:
    return f"dqm/{job}/alive/gather"
