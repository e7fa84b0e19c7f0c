"""Distributed QuickMatch (Serlin et al.): features partitioned over agents by a Voronoi
(power) diagram of descriptor space whose seeds follow from one integer.

The pure algorithm (numpy in, numpy out, no I/O) lives here and is driven by
both the in-process simulator (:func:`simulate`) and the zenoh runtime
(:mod:`dqm.runtime`), with the same payloads, so the two cannot drift apart.

=================  ===============================================================
module             holds
=================  ===============================================================
``config``         :class:`DQMConfig`, the modes (balanced, lean, paper; the runtime's gather, auto)
``costmodel``      --mode auto's predicted time to result of gather, lean, balanced; the pick
``partition``      seeds from the integer (k-means / seeded), power weights, routing
``boundary``       bisector distances (closed form, rigorous lower bounds), QP cell distances
``seeding``        the set-up every mode shares (sample, seeds, weights, sketch basis, sigma fill)
``shard``          the features an agent holds; source-side sigma
``sketch``         lower-bound sketches: the ghost pre-filter
``ghosts``         which copies travel where (one-way / two-way rules)
``balanced``       the balanced mode's agent core (rounds)
``forest``         fragments, crossing components, replay of break/merge
``contested``      the cascade's contested test and hand-down units
``cascade``        the lean and paper modes' agent core
``messages``       wire schema and validation
``protocol``       which messages each phase sends; parts, acks, traffic tables
``simulator``      all agents in one process, metered
=================  ===============================================================
"""
from ..lazy_exports import lazy_exports

#: public name -> the submodule that defines it (loaded on first use: the runtime's commands import the
#: options of :mod:`.config` without the simulator)
_PUBLIC = {"DEFAULT_MODE": ".config", "MODES": ".config", "DQMConfig": ".config", "DQMResult": ".simulator",
           "Traffic": ".simulator", "simulate": ".simulator", "image_owners": ".sources"}

__all__ = sorted(_PUBLIC)
__getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
