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

Output: the indices of the centre samples (the vocabulary entries are real samples, not means)
and the tolerance. Deterministic given the seed (CPU float32 arithmetic, fixed order).

Cost: a pass is at most ``size`` steps, each one a distance computation against the samples still
remaining, which shrink quickly for driving data. The bisection first runs on a subsample to
bracket the tolerance, then refines on all samples (see :func:`kdisks`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

__all__ = ["KDisksResult", "kdisks", "kdisks_pass", "mean_point_distance"]


def mean_point_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Mean over the points of the Euclidean distance: ``a``, ``b`` [..., P, 2] (broadcast) -> [...]."""
    return np.sqrt(((np.asarray(a) - np.asarray(b)) ** 2).sum(-1)).mean(-1)


@dataclass(frozen=True)
class KDisksResult:
    centre_indices: np.ndarray  # [K] int64, indices into the samples, in the order they were chosen
    tolerance_m: float  # the disk radius (mean point distance) of the pass that produced them
    num_samples: int  # M
    num_uncovered: int  # samples farther than tolerance_m from every centre kept
    passes: int  # k-disks passes run by the tolerance search


def kdisks_pass(samples: torch.Tensor, tolerance_m: float, max_centres: int, progress=None) -> tuple[np.ndarray, int]:
    """One k-disks pass over ``samples`` [M, P*2] float32, already in the random visiting order.

    Returns (centre rows [K <= max_centres], samples remaining when it stopped). The pass stops
    when ``max_centres`` centres are taken or nothing is left.
    """
    x = samples
    rows = torch.arange(x.shape[0])
    centres: list[int] = []
    num_points = x.shape[1] // 2
    while x.shape[0] > 0 and len(centres) < max_centres:
        centres.append(int(rows[0]))
        d = (x - x[0]).square_().view(x.shape[0], num_points, 2).sum(-1).sqrt_().mean(-1)  # [R]
        keep = d > tolerance_m
        keep[0] = False
        x, rows = x[keep], rows[keep]
        if progress is not None:
            progress.update(1)
    return np.asarray(centres, dtype=np.int64), int(x.shape[0])


def kdisks(samples: np.ndarray, size: int, seed: int = 0, subsample: int = 100_000, iterations: int = 14,
           refine_iterations: int = 6, progress: bool = True, desc: str = "k-disks") -> KDisksResult:
    """Choose ``size`` centres among ``samples`` [M, P, 2] by k-disks with a searched tolerance.

    The tolerance search is a bisection on log(tolerance) for the largest tolerance whose pass
    reaches ``size`` centres: ``iterations`` steps on a random subsample of ``subsample`` samples
    (cheap) to bracket it, then ``refine_iterations`` steps on all samples within a factor-of-2
    bracket around it. The centres are those of the best full-data pass.

    Fewer distinct samples than ``size``: every distinct sample becomes a centre (tolerance 0) and
    the result has fewer than ``size`` centres; the callers decide what to do about it (the motion
    builder augments the samples first, see ``motion.build_motion_vocabulary``).
    """
    samples = np.asarray(samples, dtype=np.float32)
    if samples.ndim != 3 or samples.shape[-1] != 2:
        raise ValueError(f"samples must be [M, P, 2], got {samples.shape}")
    m = samples.shape[0]
    if size < 1:
        raise ValueError(f"size must be >= 1, got {size}")
    rng = np.random.default_rng(seed)
    order = rng.permutation(m)
    flat = torch.from_numpy(np.ascontiguousarray(samples[order].reshape(m, -1)))

    from tqdm.auto import tqdm

    passes = 0

    def run(x: torch.Tensor, tol: float, bar_desc: str) -> tuple[np.ndarray, int]:
        nonlocal passes
        passes += 1
        with tqdm(total=size, desc=bar_desc, disable=not progress, leave=False, unit="centre") as bar:
            return kdisks_pass(x, tol, size, bar)

    # Not enough distinct samples: all of them.
    _, first_of_unique = np.unique(samples[order].reshape(m, -1), axis=0, return_index=True)
    if len(first_of_unique) <= size:
        rows = np.sort(first_of_unique)
        return KDisksResult(order[rows], 0.0, m, 0, passes)

    # Scale of the data: a typical distance between samples.
    probe = flat[: min(m, 2000)].view(-1, flat.shape[1] // 2, 2)
    scale = float((probe[:, None] - probe[None, :200]).square().sum(-1).sqrt().mean(-1).median()) or 1.0

    def bisect(x: torch.Tensor, lo: float, hi: float, steps: int, tag: str):
        """lo reaches size (or is assumed to), hi does not; returns the best (tol, centres) at lo."""
        best = None
        for it in range(steps):
            mid = math.sqrt(lo * hi)
            centres, remaining = run(x, mid, f"{desc} {tag} {it + 1}/{steps} tol={mid:.4f}")
            if len(centres) >= size:
                lo, best = mid, (mid, centres, remaining)
                if remaining == 0:  # exactly exhausted at size centres: cannot do better
                    break
            else:
                hi = mid
        return lo, hi, best

    # 1) bracket on a subsample (the first rows of the random order are a random subsample)
    sub = flat[: min(m, max(subsample, 4 * size))]
    lo, hi = scale * 1e-4, scale * 2.0
    lo, hi, found = bisect(sub, lo, hi, iterations, "bracket")
    if sub.shape[0] == m and found is not None:
        tol, centres, remaining = found
        return KDisksResult(order[centres], float(tol), m, int(remaining), passes)
    # More samples need more centres at a given tolerance, so the full-data tolerance lies at or
    # above the subsample's; the bracket is widened by 2x either way for safety.
    lo_full, hi_full = lo / 2.0, hi * 2.0
    centres, remaining = run(flat, lo_full, f"{desc} refine low tol={lo_full:.4f}")
    while len(centres) < size:  # rare: push the lower end down until it reaches size
        lo_full /= 2.0
        centres, remaining = run(flat, lo_full, f"{desc} refine low tol={lo_full:.4f}")
    best = (lo_full, centres, remaining)
    if remaining > 0:
        _, _, found = bisect(flat, lo_full, hi_full, refine_iterations, "refine")
        if found is not None:
            best = found
    tol, centres, remaining = best
    return KDisksResult(order[centres], float(tol), m, int(remaining), passes)
