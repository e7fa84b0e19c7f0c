"""The balanced mode: exact Distributed QuickMatch that spreads the work (one agent's steps).

Pure numpy in, numpy out; no I/O. The simulator and the runtime drive the same
rounds (:data:`ROUNDS`) with the same payloads, so they cannot drift apart.
Every agent owns the features of its cell (after routing) and, round by round:

``bounds``     publishes two lower-bound numbers per other cell (dqm.distributed.ghosts);
``sketch``     sends a pilot (a deterministic eighth) of the lower-bound sketches of its
               features near each cell that ships copies to it (dqm.distributed.sketch);
``request``    asks for the rest of a sketch only where it can pay: the candidates the
               pilot does not already prove plausible bound what the rest can save;
``sketch_rest`` sends the rest where asked (an empty message otherwise);
``offer``      says how many copies of its features another cell may need (one way per
               cell pair);
``ghost``      pulls the copies offered to it, a window at a time (``grant``: sender,
               offset, count; the sender answers with those copies in a ``ghost``
               message), at most two windows out, each window met with the own
               features as it arrives and then let go: the agent holds its own
               features and at most half as many copies (:attr:`BalancedCore.window`);
               the pairs among its own features are met while the first windows travel,
               pairs among copies are another agent's work;
``sums``       with every pair within reach met, returns each copy's exact partial
               density (integer sums, dqm.core.density) to the copy's owner;
``density``    completes its own features' densities (bit-identical to the centralized
               engine's) and tells the holders of its copies;
``proposal``   proposes, for every copy it holds, the nearest higher-ranked own
               feature within rho sigma of it;
``notify``     picks each own feature's parent (own candidates and proposals; ties by
               distance then id, as the engine) and tells the parents' owners about
               the crossing edges;
``fragments``  reports its crossing fragments to the leader (agent 0);
``assign``     (leader) joins fragments into components, assigns each crossing
               component to the lowest agent involved;
``component``  sends the edge lists of its fragments of components assigned elsewhere;
finally it replays break/merge of everything it keeps (dqm.distributed.forest).

The result is identical to :func:`dqm.quickmatch` on all features with the
quadratic kernel and the same rho: same sigma, same densities, same parents,
same merges (tests check labels, parents and distances).
"""
from __future__ import annotations

import time
from typing import Dict, List, Optional, Tuple

import numpy as np

from ..core import density as exact
from ..core import inverted_lists, memory, pairs, tree
from ..core.clustering import duplicate_groups, equalize_duplicates, zero_sigma_counts
from . import boundary, forest, ghosts, partition, sketch
from .config import DQMConfig
from .seeding import LEADER
from .shard import Shard

Payload = Dict[str, np.ndarray]

#: the balanced rounds after routing, in order; each is one message kind
ROUNDS = ("bounds", "sketch", "request", "sketch_rest", "offer", "ghost", "sums", "density", "proposal", "notify",
          "fragments", "assign", "component")


#: the most copies one sender may offer a cell (more than any job holds: a larger offer is refused, not allocated)
MAX_OFFER = 1 << 31


class BalancedCore:
    """One agent's state in the balanced mode. Drive it with :meth:`step` round by round."""

    def __init__(self, me: int, cfg: DQMConfig, space: Optional[sketch.SketchSpace] = None):
        self.me = me
        self.cfg = cfg
        self.m = cfg.agents
        self.rule = cfg.ghost_rule
        self.ships = ghosts.orientation(self.m, self.rule)  # ships[a, b]: a sends copies to b
        self.space = space if (space is not None and space.k > 0 and cfg.sketches) else None
        self.E = np.full((self.m, self.m), np.inf)
        self.S = np.full((self.m, self.m), np.inf)
        self.failures = 0  # arrival and consistency checks that did not hold
        self.stats: Dict[str, float] = {}
        self.cpu = 0.0
        self.round = 0
        #: the fast engine's lists over the own features, where they pay (made with the own features' pairs)
        self.lists: Optional[inverted_lists.CellLists] = None

    # ------------------------------------------------------------------ who talks to whom
    def recipients(self, name: str) -> List[int]:
        """Agents this agent sends a message to in round ``name`` (possibly an empty payload)."""
        return recipients_of(self.me, name, self.ships, self.space is not None)

    def senders(self, name: str) -> List[int]:
        """Agents whose round-``name`` message this agent needs before its next step."""
        return [a for a in range(self.m)
                if a != self.me and self.me in recipients_of(a, name, self.ships, self.space is not None)]

    # ------------------------------------------------------------------ driver entry points
    def set_shard(self, parts, seeds: np.ndarray, weights: Optional[np.ndarray]) -> None:
        """The features routed to this cell (from every source agent, itself included)."""
        t = time.process_time()
        self.own = Shard.concat(parts)
        self.seeds = np.asarray(seeds, np.float64)
        self.weights = None if weights is None else np.asarray(weights, np.float64)
        self.X = self.own.descriptors.astype(np.float64)
        self.H = boundary.bisector_lower_bounds(self.X, self.seeds, self.own.cells, self.weights)
        self.R = ghosts.reach(self.own.sigma, self.cfg.rho)
        self.n_own = len(self.own)
        self.stats.update(features_owned=float(self.n_own))
        self.cpu += time.process_time() - t

    def _count_missing(self, inputs: Dict[int, Payload]) -> None:
        """A sender of the previous round whose message is absent (it was refused) is a failure."""
        if self.round:
            self.failures += sum(a not in inputs for a in self.senders(ROUNDS[self.round - 1]))

    def _sketch_ok(self, payload: Optional[Payload]) -> bool:
        """A sketch this agent can use: present and in its own sketch space's dimension."""
        if payload is None:
            return False
        if payload["codes"].shape[1] != self.space.k or len(payload["scale"]) != self.space.k:
            self.failures += 1
            return False
        return True

    def step(self, inputs: Dict[int, Payload]) -> Dict[int, Payload]:
        """Run the next round with the previous round's messages; returns this round's messages."""
        name = ROUNDS[self.round]
        self._count_missing(inputs)
        t = time.process_time()
        out = getattr(self, f"_round_{name}")(inputs)
        self.cpu += time.process_time() - t
        self.round += 1
        if sorted(out) != self.recipients(name):
            raise RuntimeError(f"internal error: round {name!r} of agent {self.me} addressed {sorted(out)}, "
                               f"not {self.recipients(name)}")
        return out

    def finish(self, inputs: Dict[int, Payload]) -> Tuple[np.ndarray, np.ndarray]:
        """The last step: ``(ids, labels)`` of every feature this agent decides (labels local)."""
        self._count_missing(inputs)
        t = time.process_time()
        out = self._finish(inputs)
        self.cpu += time.process_time() - t
        self.stats["cpu_s"] = self.cpu
        self.stats["consistency_failures"] = float(self.failures)
        return out

    # ------------------------------------------------------------------ rounds
    def _round_bounds(self, _inputs) -> Dict[int, Payload]:
        minima, slack = ghosts.cell_summaries(self.H, self.R, self.me)
        self.E[self.me], self.S[self.me] = minima, slack
        return {b: {"minima": minima, "slack": slack} for b in self.recipients("bounds")}

    def _round_sketch(self, inputs) -> Dict[int, Payload]:
        for a, p in inputs.items():  # lengths checked on receipt (dqm.distributed.messages)
            self.E[a], self.S[a] = p["minima"], p["slack"]
        self.sketch_sent: Dict[int, List[Payload]] = {}
        self.sketch_rest: Dict[int, np.ndarray] = {}
        out = {}
        for a in self.recipients("sketch"):
            idx = np.flatnonzero(ghosts.sketch_mask(self.H[:, a], self.R, self.E[a, self.me], self.S[a, self.me],
                                                    self.rule))
            pilot = sketch.pilot_mask(self.own.ids[idx])
            self.sketch_rest[a] = idx[~pilot]
            out[a] = dict(sketch.encode(self.space, self.X[idx[pilot]], self.R[idx[pilot]]),
                          pending=int((~pilot).sum()))
            self.sketch_sent[a] = [out[a]]
        self.stats["sketches_sent"] = float(sum(int(pilot_of["codes"].shape[0]) for pilot_of in out.values()))
        return out

    def _round_request(self, inputs) -> Dict[int, Payload]:
        """For every cell this one ships to: the geometric candidates and whether the rest of the
        sketch can pay for itself (estimated on an eighth of them; the pilot then filters them all in
        :meth:`_round_offer` where the rest is asked for)."""
        self.plan: Dict[int, Tuple[np.ndarray, bool]] = {}  # cell -> (geometric candidates, rest asked for)
        self.pilots: Dict[int, Payload] = {}
        out = {}
        if self.cfg.fast:  # no certificate: the copies a pair likely needs (no sketches, no request)
            for b, idx in ghosts.likely_copies(self.H, self.R, self.recipients("offer"), self.cfg.copies_per_feature,
                                                  -self.S[:, self.me]).items():
                self.plan[b] = (idx, False)
            return out
        for b in self.recipients("offer"):
            idx = np.flatnonzero(ghosts.ship_mask(self.H[:, b], self.R, self.E[b, self.me], self.S[b, self.me],
                                                  self.rule))
            pilot = inputs.get(b) if self.space is not None else None
            if not self._sketch_ok(pilot):
                self.plan[b] = (idx, False)
            else:
                # whether the rest can pay, from a deterministic eighth of the candidates (the pilot's test of
                # all of them is needed only where the rest is asked for: else every candidate travels)
                some = np.flatnonzero(sketch.hashed_subset(self.own.ids[idx], 3))
                hit = sketch.plausible(self.space, self.X[idx[some]], self.R[idx[some]], pilot,
                                       use_their_reach=self.rule == "one-way")
                unhit = int(round((~hit).sum() * len(idx) / max(1, len(some))))
                copy_bytes = self.X.shape[1] * self.own.descriptors.itemsize + 40  # ids, image, sigma, sum, density
                want = sketch.worth_the_rest(unhit, int(pilot["pending"]), copy_bytes, self.space.k + 5)
                self.plan[b] = (idx, want)
                self.pilots[b] = pilot
        for b in self.recipients("request"):
            out[b] = {"want": int(self.plan[b][1])}
        return out

    def _round_sketch_rest(self, inputs) -> Dict[int, Payload]:
        self.requested: Dict[int, bool] = {}
        out = {}
        for a in self.recipients("sketch_rest"):
            p = inputs.get(a)
            want = bool(p is not None and p["want"])
            self.requested[a] = want
            idx = self.sketch_rest[a] if want else np.zeros(0, np.int64)
            out[a] = dict(sketch.encode(self.space, self.X[idx], self.R[idx]), pending=0)
            if want:
                self.sketch_sent[a].append(out[a])
        self.stats["sketches_sent"] += float(sum(int(v["codes"].shape[0]) for v in out.values()))
        return out

    def _round_offer(self, inputs) -> Dict[int, Payload]:
        self.shipped: Dict[int, np.ndarray] = {}
        self.shipped_to = np.zeros((self.n_own, self.m), bool)
        out = {}
        geometric = 0
        for b in self.recipients("offer"):
            cand, want = self.plan[b]
            geometric += len(cand)
            if want and self._sketch_ok(inputs.get(b)):
                one_way = self.rule == "one-way"
                hit = sketch.plausible(self.space, self.X[cand], self.R[cand], self.pilots[b], use_their_reach=one_way)
                unhit = np.flatnonzero(~hit)
                hit[unhit] = sketch.plausible(self.space, self.X[cand[unhit]], self.R[cand[unhit]], inputs[b],
                                              use_their_reach=one_way)
            else:
                hit = np.ones(len(cand), bool)  # no sketch, one not worth its rest, or a missing rest: all travel
            idx = cand[hit]
            self.shipped[b] = idx
            self.shipped_to[idx, b] = True
            out[b] = {"count": len(idx)}
        self.stats.update(ghosts_geometric=float(geometric),
                          ghosts_sent=float(sum(len(v) for v in self.shipped.values())),
                          sketch_rests_asked=float(sum(want for _, want in self.plan.values())))
        return out

    def copies(self, b: int, offset: int, count: int) -> Payload:
        """The copies for cell b from ``offset`` on, ``count`` of them at most (b's grant); an
        empty payload for a grant beyond them or from a cell this one does not ship to."""
        idx = self.shipped.get(b, np.zeros(0, np.int64))
        if offset < 0 or count < 0 or offset > len(idx) or b not in self.shipped:
            self.failures += 1
            idx = idx[:0]
        else:
            idx = idx[offset:offset + count]
        o = self.own
        return {"offset": int(offset), "ids": o.ids[idx], "image_ids": o.image_ids[idx],
                "descriptors": o.descriptors[idx], "sigma": o.sigma[idx]}

    def _arrival_check(self, a: int, p: Payload) -> int:
        """Ghosts from a that a's rule would not have sent here, recomputed on arrival.

        The receiver has everything the sender used (the ghost's descriptor and
        sigma, the seeds, its own summaries and sketches). The route and the
        bisector rule are checked for every ghost (allowing a relative 1e-9
        for float64 rounding); the sketch test, as costly as the sender's, for a
        deterministic sixteenth of them (allowing 1e-3 for float32 GEMMs that
        batch rows differently).
        """
        if len(p["ids"]) == 0:
            return 0
        Xg = p["descriptors"].astype(np.float64)
        bad = partition.route(Xg, self.seeds, self.weights) != a
        H = boundary.bisector_lower_bounds(Xg, self.seeds, np.full(len(Xg), a), self.weights)[:, self.me]
        R = ghosts.reach(p["sigma"], self.cfg.rho)
        tol = 1e-9 * (1.0 + R + H)
        if self.cfg.fast:
            ok = ghosts.likely_mask(H - tol, R + tol, -self.S[self.me, a] + tol.max(initial=0.0))
        else:
            ok = ghosts.ship_mask(H - tol, R + tol, self.E[self.me, a], self.S[self.me, a], self.rule)
        if self.space is not None and self.requested.get(a):  # a filtered with the whole sketch
            sample = np.flatnonzero(sketch.hashed_subset(p["ids"], 4))
            hit = np.zeros(len(sample), bool)
            for sk in self.sketch_sent[a]:
                hit |= sketch.plausible(self.space, Xg[sample], R[sample], sk, self.rule == "one-way", relax=1e-3)
            ok[sample] &= hit
        return int((bad | ~ok).sum())

    def _round_ghost(self, inputs) -> Dict[int, Payload]:
        """Every sender's offer (how many copies it has for this cell): plan the windows in which
        they are pulled (:meth:`next_grant`, :meth:`absorb`); nothing is sent in this round."""
        me = self.me
        self.ghost_slices: Dict[int, slice] = {}
        start = self.n_own
        src = [np.full(self.n_own, me, np.int64)]
        for a in self.senders("offer"):
            p = inputs.get(a)
            k = int(p["count"]) if p is not None else 0
            if k > MAX_OFFER:  # no cell holds that many: a hostile or broken sender, refused
                self.failures += 1
                k = 0
            self.ghost_slices[a] = slice(start, start + k)
            src.append(np.full(k, a, np.int64))
            start += k
        n_held = start
        self.held_src = np.concatenate(src)
        self.held_ids = np.concatenate([self.own.ids, np.full(n_held - self.n_own, -1, np.int64)])
        self.sums = exact.ExactSums(n_held)
        self.kept: List[Tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.kept_edges = 0
        self.windows = [(a, off, min(self.window, sl.stop - sl.start - off))
                        for a, sl in self.ghost_slices.items() for off in range(0, sl.stop - sl.start, self.window)]
        self.windows.reverse()  # popped from the end: in order
        self.pulled_rows = 0
        self.own_met = False
        n_ghost = n_held - self.n_own
        self.stats.update(ghosts_held=float(n_ghost), max_held=float(self.n_own),
                          pairs=float(self.n_own * (self.n_own - 1) // 2 + self.n_own * n_ghost),
                          ghost_windows=float(len(self.windows)))
        return {}

    @property
    def window(self) -> int:
        """Copies pulled per grant: a quarter of the cell (at least 256), so that with two grants
        out the agent holds its own features and at most half as many copies."""
        return max(256, -(-self.n_own // 4))

    def next_grant(self) -> Optional[Tuple[int, int, int]]:
        """The next window of copies to ask for: ``(sender, offset, count)``, or None when all were asked."""
        return self.windows.pop() if self.windows else None

    def pulled(self) -> bool:
        """Every copy offered to this cell has arrived and met the own features."""
        return not self.windows and self.pulled_rows == len(self.held_ids) - self.n_own

    def meet_own(self) -> bool:
        """The pairs among the own features (once, while the first copies travel); True if it ran now."""
        if self.own_met:
            return False
        t = time.process_time()
        self.own_met = True
        self._meet(self.own, np.arange(self.n_own), None)
        self.cpu += time.process_time() - t
        return True

    def absorb(self, a: int, payload: Optional[Payload], expected: int) -> int:
        """One window of copies from sender a (``expected`` of them asked for; None: refused on
        arrival): checked, met with every own feature, and let go (their sums, parent candidates
        and ids stay). Returns the copies absorbed."""
        self.meet_own()
        t = time.process_time()
        sl = self.ghost_slices.get(a)
        k = 0 if payload is None else len(payload["ids"])
        off = -1 if payload is None else int(payload["offset"])
        if payload is None or sl is None or k != expected or off < 0 or sl.start + off + k > sl.stop or \
                (k and payload["descriptors"].shape[1] != self.X.shape[1]):
            self.failures += 1
            self.pulled_rows += expected
            return 0
        self.failures += self._arrival_check(a, payload)
        rows = np.arange(sl.start + off, sl.start + off + k)
        if (self.held_ids[rows] >= 0).any():  # the same window twice
            self.failures += 1
            self.pulled_rows += expected
            return 0
        self.held_ids[rows] = payload["ids"]
        batch = Shard(np.asarray(payload["ids"], np.int64), np.asarray(payload["image_ids"], np.int64),
                      np.asarray(payload["descriptors"]).astype(self.own.descriptors.dtype, copy=False),
                      np.asarray(payload["sigma"], np.float64), np.full(k, a, np.int64))
        self.stats["max_held"] = max(self.stats["max_held"], float(self.n_own + k))
        held = Shard(*(np.concatenate([getattr(self.own, f), getattr(batch, f)]) for f in
                       ("ids", "image_ids", "descriptors", "sigma", "cells")))  # own first: the index space
        self._meet(held, np.concatenate([np.arange(self.n_own), rows]), self.n_own)
        self.pulled_rows += k
        self.cpu += time.process_time() - t
        return k

    def _meet(self, held: Shard, where: np.ndarray, cross: Optional[int]) -> None:
        """Every pair within reach among ``held`` (with ``cross = L``: only pairs of one of its first
        L rows, the own features, and one of the rest): exact kernel terms into the sums and parent
        candidates kept, both in the cell's index space (``where[k]``: the index of held row k)."""
        n = len(held)
        if n == 0:
            return
        sig = held.sigma
        active = sig > 0
        w = np.where(active, 1.0 / np.where(active, sig, 1.0) ** 2, 0.0)
        radius = self.cfg.rho * sig
        aug = pairs.Augmented(held.descriptors)
        zero = np.zeros(n)
        budget = memory.resolve_budget(None)
        cap = max(0, budget - memory.base_bytes(n, aug.dim, pairs.default_threads())) // memory.BYTES_PER_EDGE

        def tile_edges(i: np.ndarray, j: np.ndarray) -> None:
            # one tile's pairs within reach, each once: their exact kernel terms now, and only the
            # parent candidates kept, so memory does not grow with the kernel's reach
            d2 = pairs.exact_sq_distances(aug.exact, i, j)
            t_ij = np.where(active[i], exact.quadratic_terms(d2, w[i]), 0.0)  # i contributes to j
            t_ji = np.where(active[j], exact.quadratic_terms(d2, w[j]), 0.0)
            gi, gj = where[i], where[j]
            if self.rule == "two-way":  # a pair both of whose features travelled is counted at the lower agent
                keep = self._single_count(gi, gj)
                gi, gj, d2, t_ij, t_ji = gi[keep], gj[keep], d2[keep], t_ij[keep], t_ji[keep]
                i, j = i[keep], j[keep]
            self.sums.add_terms(np.concatenate([gj, gi]), np.concatenate([t_ij, t_ji]))
            d = np.sqrt(d2)
            c1 = d < radius[i]  # i child, j candidate parent
            c2 = d < radius[j]
            self.kept.append((np.concatenate([gi[c1], gj[c2]]), np.concatenate([gj[c1], gi[c2]]),
                              np.concatenate([d[c1], d[c2]])))
            self.kept_edges += len(self.kept[-1][0])
            if self.kept_edges > cap:
                raise memory.MemoryBudgetError(
                    f"agent {self.me}: the parent candidates within rho * sigma (rho {self.cfg.rho:g}) of its "
                    f"{len(self.held_ids):,} features and copies would pass its memory budget of "
                    f"{memory.format_bytes(budget)}; use a smaller rho or more agents")

        if not (self.cfg.fast and inverted_lists.lists_pay(self.n_own)):
            pairs.kernel_pass(aug, zero, zero, "quadratic", ghosts.reach(sig, self.cfg.rho), rows_limit=cross,
                              cols_from=cross, on_edges=tile_edges, undirected=True)
            return
        # the fast engine on a cell large enough for lists to pay: the pairs the centralized scan would compute,
        # from lists over the own features (made with them, before any copy), not every pair of the cell
        rad2 = pairs.search_rad2(aug, ghosts.reach(sig, self.cfg.rho))
        if cross is None:
            self.lists = inverted_lists.CellLists(aug, self.cfg.seed)
            found = self.lists.own_pairs(aug, rad2)
        else:
            found = self.lists.copy_pairs(aug, rad2, cross)
        for i, j in found:
            tile_edges(i, j)

    def _round_sums(self, inputs) -> Dict[int, Payload]:
        self.meet_own()  # no copies offered at all
        if not self.pulled():
            self.failures += 1  # the driver stepped before every window was absorbed (a bug or a refusal)
        arrived = self.held_ids[self.held_ids >= 0]
        self.failures += len(arrived) - len(np.unique(arrived))  # a copy of an own feature, or twice the same
        self.cand = tuple(np.concatenate(part) for part in zip(*self.kept)) if self.kept else \
            (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
        del self.kept
        # the distances computed: every pair, or where lists paid, what their scans met
        self.stats["pairs_computed"] = float(self.lists.computed) if self.lists is not None else self.stats["pairs"]
        out = {}
        for a in self.recipients("sums"):
            sl = self.ghost_slices[a]
            units, high = exact.pack_parts(*self.sums.parts(np.arange(sl.start, sl.stop)))
            out[a] = {"units": units, "high": high}
        return out

    def _single_count(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Two-way rule: which pairs (cell indices) to count here: not own-copy pairs that the copy's
        owner also meets and counts."""
        gi = i >= self.n_own
        gj = j >= self.n_own
        own_idx = np.where(gi, j, i)
        ghost_idx = np.where(gi, i, j)
        mixed = gi ^ gj
        a = self.held_src[ghost_idx]
        also_there = mixed & self.shipped_to[np.minimum(own_idx, max(0, self.n_own - 1)), a] & (a < self.me)
        return ~also_there

    def _round_density(self, inputs) -> Dict[int, Payload]:
        for b in self.recipients("density"):
            p = inputs.get(b)
            idx = self.shipped[b]
            if p is None or len(p["units"]) != len(idx) or (len(p["high"]) not in (0, len(idx))):
                self.failures += 1
                continue
            hi, lo = exact.unpack_parts(p["units"], p["high"])
            self.sums.add_parts(idx, hi, lo)
        # duplicates route to one cell, so the engine's duplicate rules apply here whole
        groups = duplicate_groups(self.X)
        gsize = np.bincount(groups) if len(groups) else np.zeros(0, np.int64)
        zero = self.own.sigma == 0
        dens_o = self.sums.values()[:self.n_own] + zero_sigma_counts(groups, gsize, zero) - zero
        self.density = 1.0 + equalize_duplicates(dens_o, groups, gsize)
        return {b: {"density": self.density[self.shipped[b]]} for b in self.recipients("density")}

    def _round_proposal(self, inputs) -> Dict[int, Payload]:
        n_held = len(self.held_ids)
        dens = np.full(n_held, np.nan)
        dens[:self.n_own] = self.density
        for a, sl in self.ghost_slices.items():
            p = inputs.get(a)
            if p is None or len(p["density"]) != sl.stop - sl.start:
                self.failures += 1
                continue
            dens[sl] = p["density"]
        child, cand, dist = self.cand
        ids = self.held_ids
        ok = tree.rank_order(dens[cand], dens[child], ids[cand], ids[child])  # NaN (missing) never ranks
        child, cand, dist = child[ok], cand[ok], dist[ok]
        own_child = child < self.n_own
        # own features: nearest higher-ranked among own features and held copies
        c, p_, d = child[own_child], cand[own_child], dist[own_child]
        parent, pdist, row = tree.nearest_candidates(c, ids[p_], d, self.n_own)
        owner = np.full(self.n_own, -1, np.int64)
        has = row >= 0
        owner[has] = self.held_src[p_[row[has]]]
        self.local_best = (parent, pdist, owner)
        # copies: the nearest higher-ranked own feature, proposed to the copy's owner
        gc, gp, gd = child[~own_child], cand[~own_child], dist[~own_child]
        gparent, gdist, _ = tree.nearest_candidates(gc - self.n_own, ids[gp], gd, n_held - self.n_own)
        out = {}
        for a in self.recipients("proposal"):
            sl = self.ghost_slices[a]
            loc = np.arange(sl.start - self.n_own, sl.stop - self.n_own)
            sel = loc[gparent[loc] >= 0]
            out[a] = {"index": (sel - (sl.start - self.n_own)).astype(np.int64), "parent": gparent[sel],
                      "distance": gdist[sel]}
        self.stats["proposals_sent"] = float(sum(len(v["index"]) for v in out.values()))
        return out

    def _round_notify(self, inputs) -> Dict[int, Payload]:
        parent, pdist, owner = self.local_best
        tgt, cand, dist, who = [np.arange(self.n_own)[parent >= 0]], [parent[parent >= 0]], \
            [pdist[parent >= 0]], [owner[parent >= 0]]
        for b in self.recipients("offer"):
            p = inputs.get(b)
            idx = self.shipped.get(b, np.zeros(0, np.int64))
            if p is None:
                self.failures += 1
                continue
            k = np.asarray(p["index"], np.int64)
            valid = (k >= 0) & (k < len(idx)) & (np.asarray(p["parent"]) >= 0)
            self.failures += int((~valid).sum())
            k = k[valid]
            tgt.append(idx[k])
            cand.append(np.asarray(p["parent"], np.int64)[valid])
            dist.append(np.asarray(p["distance"], np.float64)[valid])
            who.append(np.full(len(k), b, np.int64))
        tgt, cand, dist, who = (np.concatenate(v) for v in (tgt, cand, dist, who))
        self.parent, self.pdist, row = tree.nearest_candidates(tgt, cand, dist, self.n_own)
        self.parent_owner = np.full(self.n_own, -1, np.int64)
        self.parent_owner[row >= 0] = who[row[row >= 0]]
        ids = self.own.ids
        local = self.parent_owner == self.me
        local_parent = np.full(self.n_own, -1, np.int64)
        local_parent[local] = np.searchsorted(ids, self.parent[local])
        self.roots = forest.fragment_roots(local_parent)
        crossing_out = (self.parent >= 0) & ~local
        self.out_roots = np.flatnonzero(crossing_out)  # fragment roots with a parent elsewhere
        self.stats["crossing_edges"] = float(len(self.out_roots))
        out = {}
        for b in self.recipients("notify"):
            sel = self.out_roots[self.parent_owner[self.out_roots] == b]
            out[b] = {"child": ids[sel], "parent": self.parent[sel]}
        return out

    def _round_fragments(self, inputs) -> Dict[int, Payload]:
        ids = self.own.ids
        child_key, child_agent, parent_key = [], [], []
        for a in sorted(inputs):
            p = inputs[a]
            par = np.asarray(p["parent"], np.int64)
            pos = np.minimum(np.searchsorted(ids, par), max(0, self.n_own - 1))
            found = ids[pos] == par if self.n_own else np.zeros(len(par), bool)
            self.failures += int((~found).sum())
            child_key.append(np.asarray(p["child"], np.int64)[found])
            child_agent.append(np.full(int(found.sum()), a, np.int64))
            parent_key.append(ids[self.roots[pos[found]]])
        cat = (lambda v: np.concatenate(v) if v else np.zeros(0, np.int64))  # noqa: E731
        edges = {"child_key": cat(child_key), "child_agent": cat(child_agent), "parent_key": cat(parent_key)}
        self.crossing = np.union1d(ids[self.out_roots], edges["parent_key"])
        if self.me == LEADER:
            self.leader_edges = {LEADER: edges}
            return {}
        return {LEADER: edges}

    def _round_assign(self, inputs) -> Dict[int, Payload]:
        if self.me != LEADER:
            return {}
        all_edges = dict(self.leader_edges)
        all_edges.update(inputs)
        ck, ca, pk, pa = [], [], [], []
        for b in sorted(all_edges):
            e = all_edges[b]
            ck.append(np.asarray(e["child_key"], np.int64))
            ca.append(np.asarray(e["child_agent"], np.int64))
            pk.append(np.asarray(e["parent_key"], np.int64))
            pa.append(np.full(len(e["parent_key"]), b, np.int64))
        keys, agents, targets = forest.assign_components(*(np.concatenate(v) for v in (ck, ca, pk, pa)))
        self.stats["crossing_components_features_keys"] = float(len(keys))
        self.assigned_here = {"key": keys[agents == LEADER], "target": targets[agents == LEADER]}
        return {b: {"key": keys[agents == b], "target": targets[agents == b]} for b in self.recipients("assign")}

    def _round_component(self, inputs) -> Dict[int, Payload]:
        a = self.assigned_here if self.me == LEADER else inputs.get(LEADER)
        if a is None:
            self.failures += 1
            a = {"key": np.zeros(0, np.int64), "target": np.zeros(0, np.int64)}
        keys = np.asarray(a["key"], np.int64)
        targets = np.asarray(a["target"], np.int64)
        if not np.array_equal(np.sort(keys), self.crossing):
            self.failures += 1
        ids = self.own.ids
        frag_key = ids[self.roots] if self.n_own else np.zeros(0, np.int64)
        order = np.argsort(keys)
        keys, targets = keys[order], targets[order]
        dest = np.full(self.n_own, self.me, np.int64)
        if len(keys) and self.n_own:
            pos = np.minimum(np.searchsorted(keys, frag_key), len(keys) - 1)
            hit = keys[pos] == frag_key
            dest[hit] = targets[pos[hit]]
        out = {}
        o = self.own
        for b in self.recipients("component"):
            sel = np.flatnonzero(dest == b)
            out[b] = {"ids": o.ids[sel], "image_ids": o.image_ids[sel], "sigma": o.sigma[sel],
                      "parent": self.parent[sel], "distance": self.pdist[sel]}
        self.keep = np.flatnonzero(dest == self.me)
        self.stats["features_handed"] = float(self.n_own - len(self.keep))
        return out

    def _finish(self, inputs) -> Tuple[np.ndarray, np.ndarray]:
        o = self.own
        k = self.keep
        parts = [(o.ids[k], o.image_ids[k], o.sigma[k], self.parent[k], self.pdist[k])]
        for b in sorted(inputs):
            p = inputs[b]
            parts.append((p["ids"], p["image_ids"], p["sigma"], p["parent"], p["distance"]))
        ids, img, sig, par, dist = (np.concatenate([np.asarray(p[f]) for p in parts]) for f in range(5))
        order = np.argsort(ids, kind="stable")
        ids, img, sig, par, dist = ids[order], img[order], sig[order], par[order], dist[order]
        labels, missing = forest.replay(ids, img, sig, par, dist, self.cfg.rho)
        self.failures += missing
        self.stats["features_final"] = float(len(ids))
        self.stats["max_held"] = max(self.stats.get("max_held", 0.0), float(len(ids)))
        return ids.astype(np.int64), labels.astype(np.int64)


def recipients_of(a: int, name: str, ships: np.ndarray, sketches: bool) -> List[int]:
    """Recipients of agent a in round ``name``: the one rule every agent evaluates."""
    others = [b for b in range(len(ships)) if b != a]
    if name in ("bounds", "notify", "component"):
        return others
    if name in ("sketch", "sketch_rest"):
        return [b for b in others if ships[b, a]] if sketches else []
    if name == "request":
        return [b for b in others if ships[a, b]] if sketches else []
    if name in ("offer", "density"):
        return [b for b in others if ships[a, b]]
    if name == "ghost":  # pulled window by window (grant, then copies), not sent as a round
        return []
    if name in ("sums", "proposal"):
        return [b for b in others if ships[b, a]]
    if name == "fragments":
        return [LEADER] if a != LEADER else []
    if name == "assign":
        return others if a == LEADER else []
    raise ValueError(f"unknown round {name!r}")
