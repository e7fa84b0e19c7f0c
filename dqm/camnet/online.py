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
from .pipeline import Matches, quickmatch_matches


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
        self.refs = list(refs)
        self._frame: Dict[int, int] = {}  # camera -> image id of its current frame
        self._feats: Dict[int, ImageFeatures] = {}  # camera -> features of its current frame
        self._last_step: Dict[int, int] = {}
        self.update_times: List[float] = []
        self.set_sizes: List[int] = []
        self.n_events: List[int] = []
        D = np.vstack([f.descriptors for f in refs])
        ids = np.concatenate([np.full(len(f), r, np.int64) for r, f in enumerate(refs)])
        t = time.perf_counter()
        self.om.add(D, ids)
        self.reference_time = time.perf_counter() - t

    def image_id(self, step: int, camera: int) -> int:
        return self.n_refs + int(step) * self.n_cameras + int(camera)

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
            self._feats.pop(camera)
        if len(feats):
            n_ev += len(self.om.add(feats.descriptors, np.full(len(feats), new, np.int64)).events)
            self._frame[camera] = new
            self._feats[camera] = feats
        self.update_times.append(time.perf_counter() - t)
        self.n_events.append(n_ev)
        self._last_step[camera] = step
        self.set_sizes.append(int(self.om.n_features))
        return self.matches(camera)

    def matches(self, camera: int) -> List[Matches]:
        """``[(reference feature indices, camera feature indices)]`` per reference, from the current clusters."""
        img = self._frame.get(camera)
        if img is None:
            return [(np.zeros(0, np.int64), np.zeros(0, np.int64)) for _ in range(self.n_refs)]
        # the references, then this frame: each image's features in their own order (arrival order)
        ids = np.asarray(self.om.image_ids)
        mine = (ids < self.n_refs) | (ids == img)
        matches, _ = quickmatch_matches(self.refs, [self._feats[camera]], self.om.rho,
                                        labels=np.asarray(self.om.labels)[mine])
        return matches[0]

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
