"""Padded batches that change one row at a time: the two operations every batched structure of the
project (the rollout state and its KV cache, the environment's scene batch) uses to put a new scene
in place of a finished one.

Rows are the leading dimension (scenes, groups); the other dimensions are budgets (agent slots,
road pieces, frames) that grow when a new row needs more and never shrink. Padding is written with
a fill value that the owner's masks already treat as absent (-1 indices, False masks, zeros).
"""

from __future__ import annotations

import numpy as np
import torch


def pad_stack(arrays: list[np.ndarray], size: tuple[int, ...], fill=0) -> np.ndarray:
    """``arrays`` (one per row, each no larger than ``size``) stacked into [rows, *size], padded with ``fill``."""
    out = np.full((len(arrays), *size), fill, dtype=arrays[0].dtype)
    for i, a in enumerate(arrays):
        out[(i, *[slice(0, k) for k in a.shape])] = a
    return out


def grow(t: torch.Tensor, sizes: dict[int, int], fill=0) -> torch.Tensor:
    """``t`` padded with ``fill`` at the end of each dimension ``d`` of ``sizes`` ({dim: size}) that is
    smaller than ``size`` (the same tensor when none is)."""
    shape = list(t.shape)
    for d, size in sizes.items():
        shape[d] = max(shape[d], int(size))
    if list(t.shape) == shape:
        return t
    out = t.new_full(shape, fill)
    out[tuple(slice(0, s) for s in t.shape)] = t
    return out


def put_rows(dst: torch.Tensor, rows: torch.Tensor, src: torch.Tensor, fill=0) -> None:
    """``dst[rows] = src`` in place, with ``src`` [len(rows), ...] no larger than ``dst``'s rows in
    any dimension: the part of each row that ``src`` does not cover is set to ``fill``."""
    if tuple(src.shape[1:]) == tuple(dst.shape[1:]):
        dst[rows] = src.to(dst.device, dst.dtype)
        return
    if any(s > d for s, d in zip(src.shape[1:], dst.shape[1:])):
        raise ValueError(f"rows of shape {tuple(src.shape[1:])} do not fit in {tuple(dst.shape[1:])}: grow the destination first")
    block = dst.new_full((len(rows), *dst.shape[1:]), fill)
    block[tuple(slice(0, s) for s in src.shape)] = src.to(dst.device, dst.dtype)
    dst[rows] = block


__all__ = ["grow", "put_rows"]
