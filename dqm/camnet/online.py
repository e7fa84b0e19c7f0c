"""Online QuickMatch in the camera network: clusters kept up to date as frames arrive.

One :class:`dqm.core.online.OnlineQuickMatch` serves a whole run. The
reference images are added once and stay; then frames arrive one camera at a
time in time order. When camera c's frame of step t arrives, c's previous frame
(step t-1) is removed, the new one is added, and c is scored right then on the
current clusters: a sliding window of one frame per camera, in which the
cameras before c already hold their step-t frame and the ones after c still
hold their step-(t-1) frame (none at step 0).

Matches of camera c with reference r are co-memberships, as in
:func:`dqm.camnet.pipeline.quickmatch_matches`. Right after the last camera of
a step arrived the set holds exactly the references and every camera's frame
of that step, in the batch order (references, then cameras): the labels are
then those of batch QuickMatch with the quadratic kernel over that step.
"""
from __future__ import annotations

import time
from typing import Dict, List, Optional, Sequence

import numpy as np

from ..validation import InputError
from ..vision.features import ImageFeatures
from .pipeline import Matches


class OnlineMatcher:
    """Online QuickMatch over the references and each camera's latest frame.

    Image ids: reference r is ``r``; camera c's frame of step t is
    ``R + t * n_cameras + c`` (R references), so ids grow in arrival order and
    an id is never reused. ``update_times`` holds, per frame, the seconds of
    its remove + add; ``set_sizes`` the number of features clustered after it.
    """

    def __init__(self, refs: Sequence[ImageFeatures], n_cameras: int, rho: float, parent: str = "any"):
        from ..core.online import OnlineQuickMatch

        if int(n_cameras) != n_cameras or n_cameras < 1:
            raise InputError(f"n_cameras must be a positive integer, got {n_cameras!r}")
        if not refs:
            raise InputError("no reference images")
        self.n_refs = len(refs)
        self.n_cameras = int(n_cameras)
        self.om = OnlineQuickMatch(rho=rho, kernel="quadratic", parent=parent)
        self._first_key: Dict[int, int] = {}  # image id -> key of its first feature
        self._frame: Dict[int, int] = {}  # camera -> image id of its current frame
        self._last_step: Dict[int, int] = {}
        self.update_times: List[float] = []
        self.set_sizes: List[int] = []
        self.n_events: List[int] = []
        D = np.vstack([f.descriptors for f in refs])
        ids = np.concatenate([np.full(len(f), r, np.int64) for r, f in enumerate(refs)])
        t = time.perf_counter()
        self.om.add(D, ids)
        self.reference_time = time.perf_counter() - t
        self._note_keys(range(self.n_refs))

    def image_id(self, step: int, camera: int) -> int:
        return self.n_refs + int(step) * self.n_cameras + int(camera)

    def _note_keys(self, images) -> None:
        ids, keys = np.asarray(self.om.image_ids), np.asarray(self.om.keys)
        for i in images:
            sel = keys[ids == i]
            if len(sel):
                if not np.array_equal(sel, np.arange(sel[0], sel[0] + len(sel))):
                    raise RuntimeError(f"image {i}'s features did not get consecutive keys")
                self._first_key[i] = int(sel[0])

    def update(self, step: int, camera: int, feats: ImageFeatures) -> List[Matches]:
        """Camera ``camera``'s frame of ``step`` arrives: replace its previous one; its matches with each reference."""
        if not 0 <= camera < self.n_cameras:
            raise InputError(f"camera {camera} out of range (0..{self.n_cameras - 1})")
        if step <= self._last_step.get(camera, -1):
            raise InputError(f"camera {camera}: frames must arrive in time order (step {step} after "
                             f"{self._last_step[camera]})")
        new = self.image_id(step, camera)
        t = time.perf_counter()
        n_ev = 0
        old = self._frame.pop(camera, None)
        if old is not None:
            n_ev += len(self.om.remove(old).events)
            self._first_key.pop(old, None)
        if len(feats):
            n_ev += len(self.om.add(feats.descriptors, np.full(len(feats), new, np.int64)).events)
            self._frame[camera] = new
        self.update_times.append(time.perf_counter() - t)
        self.n_events.append(n_ev)
        self._last_step[camera] = step
        self.set_sizes.append(int(self.om.n_features))
        if len(feats):
            self._note_keys([new])
        return self.matches(camera)

    def matches(self, camera: int) -> List[Matches]:
        """``[(reference feature indices, camera feature indices)]`` per reference, from the current clusters."""
        img = self._frame.get(camera)
        empty = (np.zeros(0, np.int64), np.zeros(0, np.int64))
        if img is None:
            return [empty for _ in range(self.n_refs)]
        labels = np.asarray(self.om.labels)
        ids, keys = np.asarray(self.om.image_ids), np.asarray(self.om.keys)
        K = int(labels.max()) + 1 if len(labels) else 0
        cam_of = np.full(K, -1, np.int64)  # cluster -> the camera's feature in it (C2: at most one)
        mine = ids == img
        cam_of[labels[mine]] = keys[mine] - self._first_key[img]
        out = []
        for r in range(self.n_refs):
            sel = ids == r
            local_r = keys[sel] - self._first_key[r]
            local_c = cam_of[labels[sel]]
            both = local_c >= 0
            order = np.argsort(labels[sel][both], kind="stable")  # cluster order, as quickmatch_matches
            out.append((local_r[both][order], local_c[both][order]))
        return out

    def current_images(self) -> List[Optional[int]]:
        """Image id of each camera's current frame (None: no frame yet)."""
        return [self._frame.get(c) for c in range(self.n_cameras)]

    def stats(self) -> Dict[str, float]:
        """Update times (seconds per frame: remove + add) and set sizes over the frames so far."""
        t = np.asarray(self.update_times, float)
        n = np.asarray(self.set_sizes, float)
        if not len(t):
            return {"frames": 0}
        return {"frames": int(len(t)), "update_mean_s": float(t.mean()), "update_median_s": float(np.median(t)),
                "update_max_s": float(t.max()), "update_total_s": float(t.sum()),
                "references_s": float(self.reference_time), "features_mean": float(n.mean()),
                "features_max": int(n.max()), "events_mean": float(np.mean(self.n_events))}
