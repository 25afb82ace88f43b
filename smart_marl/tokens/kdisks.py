"""k-disks clustering: the vocabulary builder behind both the motion and the road tokens (tokens stage).

Input: ``M`` samples, each a fixed-size set of ``P`` 2-D points (a motion snippet's box contour, 6
poses x 4 corners = 24 points; a road piece's resampled points, 11). The distance between two
samples is the *mean point distance*: the mean over the ``P`` points of the Euclidean distance
between corresponding points (metres).

k-disks (SMART sec. 3.1): walk the samples in a random order fixed by the seed; the first sample
not yet removed becomes a centre and every remaining sample within ``tolerance_m`` of it is
removed; repeat. A larger tolerance gives fewer centres. :func:`kdisks` searches the tolerance by
bisection for the *largest* tolerance whose pass still yields the requested number of centres,
then keeps the first ``size`` centres of that pass, so that the samples left uncovered are few.

A given tolerance instead (``kdisks(..., tolerance_m=r)``, smaller than the covering one): the first
``size`` centres of one pass at that radius. The visiting order is random, so the early centres
fall where the samples are dense: the tokens go to the common motions at a fine resolution and
rare ones (sharp turns, hard braking) are left to their nearest token. On SUMO-built vehicle
vocabularies this is what makes real straight driving rebuild without a turning jitter
(docs/model_card.md).

Output: the indices of the centre samples (the vocabulary entries are real samples, not means)
and the tolerance. Deterministic given the seed (CPU float32 arithmetic, fixed order).

Cost: a pass is at most ``size`` steps. A step does not scan every sample: linear keys of the
points bound the distance from below (see ``_Index``), so the samples are sorted by one key once,
and a step computes exact distances only for the live samples whose keys all lie within the
tolerance of the centre's (a binary search plus filters). Passes are cheap enough that the bisection runs on all samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from tqdm.auto import tqdm

__all__ = ["KDisksResult", "kdisks", "kdisks_pass", "mean_point_distance", "point_distance_matrices"]


def mean_point_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Mean over the points of the Euclidean distance: ``a``, ``b`` [..., P, 2] (broadcast) -> [...]."""
    return np.sqrt(((np.asarray(a) - np.asarray(b)) ** 2).sum(-1)).mean(-1)


def point_distance_matrices(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Distances between corresponding points of every pair: ``a`` [N, P, 2], ``b`` [V, P, 2] ->
    [P, N, V] (the matchers average them, possibly weighted). Computed point by point, directly (no
    ``|a|^2 + |b|^2 - 2ab`` cancellation), without the [N, V, P, 2] difference tensor: 6-10x faster
    than broadcasting on the CPU, equal to it within float rounding."""
    return torch.cdist(a.transpose(0, 1).contiguous(), b.transpose(0, 1).contiguous(),
                       compute_mode="donot_use_mm_for_euclid_dist")


@dataclass(frozen=True)
class KDisksResult:
    centre_indices: np.ndarray  # [K] int64, indices into the samples, in the order they were chosen
    tolerance_m: float  # the disk radius (mean point distance) of the pass that produced them
    num_samples: int  # M
    num_uncovered: int  # samples farther than tolerance_m from every centre kept
    passes: int  # k-disks passes run by the tolerance search


def _key_directions(num_points: int, phase: float, offset_rad: float) -> np.ndarray:
    """Unit vectors [P, 2], one per point, at angles ``offset + (pi/3) sin(2.39 i + phase)``."""
    ang = offset_rad + (np.pi / 3) * np.sin(2.39 * np.arange(num_points) + phase)
    return np.stack([np.cos(ang), np.sin(ang)], -1).astype(np.float32)


class _Index:
    """Samples sorted by a scalar key, for the candidate search of a k-disks step.

    Any key ``k(p) = mean_i a_i . p_i`` with unit vectors ``a_i`` satisfies
    ``|k(p) - k(q)| <= mean_i |p_i - q_i|`` (the distance), so only samples whose keys are all
    within the tolerance of the centre's can be within it. The sort key mixes x with per-point
    varying directions (so that boxes turning in place, which share their mean point, still differ
    in key); the filter keys are the mean point's x and y and a second mixed key.
    """

    def __init__(self, samples: np.ndarray):
        p = samples.shape[1]
        primary = (samples * _key_directions(p, 0.0, 0.0)).sum(-1).mean(-1)  # [M]
        filters = np.stack([samples[..., 0].mean(-1), samples[..., 1].mean(-1),
                            (samples * _key_directions(p, 1.0, np.pi / 2)).sum(-1).mean(-1)], -1)  # [M, 3]
        self.sort = np.argsort(primary, kind="stable")
        self.key = np.ascontiguousarray(primary[self.sort])
        self.filters = np.ascontiguousarray(filters[self.sort])
        self.pts = np.ascontiguousarray(samples[self.sort])  # [M, P, 2], sorted
        self.rank = np.empty_like(self.sort)
        self.rank[self.sort] = np.arange(len(self.sort))

    def run(self, order: np.ndarray, tolerance_m: float, max_centres: int, progress=None) -> tuple[np.ndarray, int]:
        """One pass visiting samples in ``order``; returns (centre sample indices, samples left)."""
        m = len(self.key)
        alive = np.ones(m, bool)  # in sorted positions
        order_pos = self.rank[order]  # visiting order as sorted positions
        centres: list[int] = []
        ptr, left, tol = 0, m, float(tolerance_m)
        while left > 0 and len(centres) < max_centres:
            while True:  # next live sample in visiting order
                seg = np.flatnonzero(alive[order_pos[ptr : ptr + 4096]])
                if len(seg):
                    ptr += int(seg[0])
                    break
                ptr += 4096
            c = int(order_pos[ptr])
            centres.append(c)
            lo = int(np.searchsorted(self.key, self.key[c] - tol, "left"))
            hi = int(np.searchsorted(self.key, self.key[c] + tol, "right"))
            near = (np.abs(self.filters[lo:hi] - self.filters[c]) <= tol).all(-1)
            cand = lo + np.flatnonzero(alive[lo:hi] & near)
            d = np.sqrt(((self.pts[cand] - self.pts[c]) ** 2).sum(-1)).mean(-1)
            gone = cand[d <= tol]
            alive[gone] = False
            left -= len(gone)  # the centre itself is among them (distance 0)
            if progress is not None:
                progress.update(1)
        left = int(alive.sum())
        return self.sort[np.asarray(centres, dtype=np.int64)], left


def kdisks_pass(samples: np.ndarray, tolerance_m: float, max_centres: int, seed: int = 0) -> tuple[np.ndarray, int]:
    """One k-disks pass over ``samples`` [M, P, 2] in the random order of ``seed``: (centre indices, samples left)."""
    samples = np.asarray(samples, np.float32)
    order = np.random.default_rng(seed).permutation(len(samples))
    return _Index(samples).run(order, tolerance_m, max_centres)


def kdisks(samples: np.ndarray, size: int, seed: int = 0, iterations: int = 24, progress: bool = True,
           desc: str = "k-disks", tolerance_m: float | None = None) -> KDisksResult:
    """Choose ``size`` centres among ``samples`` [M, P, 2] by k-disks with a searched tolerance
    (or the given ``tolerance_m``: the first ``size`` centres of a pass at that radius, see the
    module docstring; when that pass covers every sample with fewer centres, the search runs).

    The search is a bisection on log(tolerance) for the largest tolerance whose pass reaches
    ``size`` centres (at most ``iterations`` passes; it stops early when a pass reaches ``size``
    centres with nothing left uncovered, or the bracket is within 1 %). All passes visit the
    samples in the same random order (the seed's).

    Fewer distinct samples than ``size``: every distinct sample becomes a centre (tolerance 0) and
    the result has fewer than ``size`` centres; the callers decide what to do about it (the motion
    builder augments the samples first, see ``motion.build_motion_vocabulary``).
    """
    samples = np.asarray(samples, dtype=np.float32)
    if samples.ndim != 3 or samples.shape[-1] != 2:
        raise ValueError(f"samples must be [M, P, 2], got {samples.shape}")
    if size < 1:
        raise ValueError(f"size must be >= 1, got {size}")
    m = samples.shape[0]
    order = np.random.default_rng(seed).permutation(m)
    index = _Index(samples)
    passes = 0

    def run(tol: float, tag: str) -> tuple[np.ndarray, int]:
        nonlocal passes
        passes += 1
        with tqdm(total=size, desc=f"{desc} {tag} tol={tol:.5f}", disable=not progress, leave=False, unit="centre") as bar:
            return index.run(order, tol, size, bar)

    centres, left = run(0.0, "distinct")
    if len(centres) < size:  # fewer distinct samples than tokens: all of them
        return KDisksResult(order[:0].astype(np.int64) if m == 0 else centres, 0.0, m, 0, passes)
    best = (0.0, centres, left)
    if left == 0:
        return KDisksResult(centres, 0.0, m, 0, passes)
    if tolerance_m is not None and tolerance_m > 0:
        centres, left = run(float(tolerance_m), "given")
        if len(centres) >= size:
            return KDisksResult(np.asarray(centres, np.int64), float(tolerance_m), m, int(left), passes)
    probe = samples[order[: min(m, 500)]]
    scale = float(np.median(np.sqrt(((probe[:, None] - probe[None, :100]) ** 2).sum(-1)).mean(-1))) or 1.0
    lo, hi = scale * 1e-6, scale * 4.0
    for it in range(iterations):
        mid = math.sqrt(lo * hi)
        centres, left = run(mid, f"{it + 1}/{iterations}")
        if len(centres) >= size:
            lo, best = mid, (mid, centres, left)
            if left == 0:
                break
        else:
            hi = mid
        if hi / lo < 1.01:
            break
    tol, centres, left = best
    return KDisksResult(np.asarray(centres, np.int64), float(tol), m, int(left), passes)
