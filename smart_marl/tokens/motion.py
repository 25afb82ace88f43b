"""Motion tokens (tokens stage): Scenario tracks -> 0.5 s motion tokens -> poses again.

What comes in: a :class:`~smart_marl.scenario.Scenario` (or plain pose arrays). What goes out:
:class:`MotionTokens` (token ids per agent and token step, their validity, the poses the token
sequence reaches), which the SMART model trains on and the environment acts in; and back, 10 Hz
poses from token ids (:func:`detokenize`).

Definitions (SMART sec. 3.1, the reference code rainmaker22/SMART):

* A token spans ``FRAMES_PER_TOKEN = 5`` frames (0.5 s). Its *snippet* is 6 poses (x, y, heading):
  the start pose and the 5 following frames, in the agent's frame at the snippet start (so pose 0
  is always (0, 0, 0)).
* Its *contour* is the 4 corners of a fixed-size box per type at each of the 6 poses, [6, 4, 2],
  corner order left-front, right-front, right-back, left-back. Box sizes (length x width) are the
  reference code's: vehicle 4.8 x 2.0 m, pedestrian 1.0 x 1.0 m, cyclist 2.0 x 1.0 m (read off
  its published ``cluster_frame_5_2048.pkl``).
* A vocabulary per type (:class:`TypeVocab`) is built by k-disks (:mod:`.kdisks`) on the 24
  contour points of the data's snippets (all 6 poses; the reference script clusters on the final
  pose's 4 corners only), distance = mean corner distance; the tokens are real snippets.
* The token grid: boundaries at frames ``current_frame % 5 + 5 k`` (k = 0, 1, ...; for WOMD, current
  frame 10: frames 0, 5, ..., 90, so 18 tokens and the current frame is boundary 2). Token k spans
  boundary k to k + 1 and is *valid* when the track is valid at both boundary frames (as in the
  reference code); frames between are used where valid.
* Rolling matching (:func:`tokenize_tracks`): token k is chosen in the frame of the pose that the
  previously matched tokens *reached*, not the ground truth's, so errors cannot accumulate
  unseen; it minimises the mean corner distance between the token's contour and the ground-truth
  box contour over the token's frames 1..5 that are valid (``match="contour"``, the default) or at
  its last frame only (``match="end"``, the reference code's choice). When token k - 1 is invalid
  (the agent appears late, or after a gap) token k starts from the ground truth at its first
  boundary (re-anchoring). Frames of a late agent before its first valid boundary are not
  tokenized. Parked cars take a (near) zero-motion token; reversing vehicles a token moving
  backwards in the agent frame, when the data the vocabulary was built from has them.
* Matching one move to one token (:func:`match_token_ends`: the token whose end is nearest a
  displacement, e.g. an agent that appears late or one replayed from the log; :func:`match_token_path`:
  the token whose 5 poses follow a target path best, looking one token ahead, for scripted agents).
* Training noise: with ``noise_topk = k > 1`` the token is drawn uniformly among the k nearest
  (with probability ``noise_prob``, default 1 like the reference), from a seeded generator; the
  rolling continues from the noised token's pose.
"""

from __future__ import annotations

import hashlib
import math
import warnings
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping

import numpy as np
import torch

from ..scenario import DT_S, AgentType, Scenario, wrap_angle
from .kdisks import kdisks, point_distance_matrices

__all__ = [
    "BOX_SIZE_M", "FRAMES_PER_TOKEN", "MOTION_TYPES", "POSES_PER_TOKEN", "TOKEN_S", "TYPE_KEYS", "VOCABULARY_VERSION",
    "MotionTokens", "MotionVocabulary", "TypeVocab",
    "augment_snippets", "box_contour", "build_motion_vocabulary", "collect_snippets", "compose_poses",
    "detokenize", "hash_arrays", "match_token_ends", "match_token_path", "motion_vocabulary_hash", "path_heading_weight",
    "place_tokens", "relative_poses", "reconstruct",
    "snippets_from_tracks", "token_boundaries", "token_poses_from_contours", "tokenize_motion", "tokenize_tracks",
    "uniform_grid_vocabulary",
]

FRAMES_PER_TOKEN = 5
TOKEN_S = FRAMES_PER_TOKEN * DT_S  # 0.5 s: one token step
POSES_PER_TOKEN = FRAMES_PER_TOKEN + 1
MOTION_TYPES = (AgentType.VEHICLE, AgentType.PEDESTRIAN, AgentType.CYCLIST)
TYPE_KEYS = {AgentType.VEHICLE: "veh", AgentType.PEDESTRIAN: "ped", AgentType.CYCLIST: "cyc"}
BOX_SIZE_M = {AgentType.VEHICLE: (4.8, 2.0), AgentType.PEDESTRIAN: (1.0, 1.0), AgentType.CYCLIST: (2.0, 1.0)}
"""(length, width) of the fixed box whose corners make a token's contour, per type."""


# ------------------------------------------------------------------------------------ geometry
def box_contour(poses: np.ndarray, length_m: float, width_m: float) -> np.ndarray:
    """Corners [..., 4, 2] (left-front, right-front, right-back, left-back) of boxes at ``poses`` [..., 3]."""
    poses = np.asarray(poses)
    c, s = np.cos(poses[..., 2]), np.sin(poses[..., 2])
    hl, hw = 0.5 * length_m, 0.5 * width_m
    local = np.array([[hl, hw], [hl, -hw], [-hl, -hw], [-hl, hw]], dtype=poses.dtype)  # [4, 2]
    x = poses[..., None, 0] + c[..., None] * local[:, 0] - s[..., None] * local[:, 1]
    y = poses[..., None, 1] + s[..., None] * local[:, 0] + c[..., None] * local[:, 1]
    return np.stack([x, y], axis=-1)


def token_poses_from_contours(contour: torch.Tensor) -> torch.Tensor:
    """Token poses [V, 6, 3] from contours [V, 6, 4, 2] (the inverse of :func:`box_contour`):
    position = the box centre, heading = from the back edge's middle to the front edge's middle."""
    centre = contour.mean(-2)  # (V, 6, 2)
    axis = (contour[..., 0, :] + contour[..., 1, :]) - (contour[..., 2, :] + contour[..., 3, :])  # (V, 6, 2)
    return torch.cat([centre, torch.atan2(axis[..., 1], axis[..., 0])[..., None]], -1)


def relative_poses(poses: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """``poses`` [..., 3] expressed in the frame of ``origin`` [..., 3] (broadcast)."""
    poses, origin = np.asarray(poses), np.asarray(origin)
    c, s = np.cos(origin[..., 2]), np.sin(origin[..., 2])
    dx, dy = poses[..., 0] - origin[..., 0], poses[..., 1] - origin[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(poses[..., 2] - origin[..., 2])], axis=-1)


def compose_poses(origin: np.ndarray, local: np.ndarray) -> np.ndarray:
    """Poses ``local`` [..., 3] given in the frame of ``origin`` [..., 3] -> the outer frame."""
    origin, local = np.asarray(origin), np.asarray(local)
    c, s = np.cos(origin[..., 2]), np.sin(origin[..., 2])
    x = origin[..., 0] + c * local[..., 0] - s * local[..., 1]
    y = origin[..., 1] + s * local[..., 0] + c * local[..., 1]
    return np.stack([x, y, wrap_angle(origin[..., 2] + local[..., 2])], axis=-1)


def token_boundaries(current_frame: int, num_frames: int) -> np.ndarray:
    """Frames of the token grid: ``current_frame % 5 + 5 k`` below ``num_frames`` (see module doc)."""
    return np.arange(int(current_frame) % FRAMES_PER_TOKEN, int(num_frames), FRAMES_PER_TOKEN, dtype=np.int64)


# ---------------------------------------------------------------------------------- vocabulary
@dataclass(frozen=True, eq=False)
class TypeVocab:
    """One agent type's motion tokens."""

    poses: np.ndarray  # [V, 6, 3] float32, x, y, heading of each token's 6 poses, token start frame
    contour: np.ndarray  # [V, 6, 4, 2] float32, box corners at each pose
    length_m: float
    width_m: float
    tolerance_m: float = 0.0  # the k-disks disk radius (mean corner distance); 0 when not k-disks
    requested_size: int = 0
    num_samples: int = 0  # snippets it was built from (after augmentation)
    num_real_samples: int = 0  # of which taken from scenes

    @property
    def size(self) -> int:
        return int(self.poses.shape[0])

    @classmethod
    def from_poses(cls, poses: np.ndarray, length_m: float, width_m: float, **kwargs) -> "TypeVocab":
        poses = np.asarray(poses, np.float32)
        return cls(poses=poses, contour=box_contour(poses, length_m, width_m).astype(np.float32),
                   length_m=float(length_m), width_m=float(width_m), **kwargs)


@dataclass(frozen=True, eq=False)
class MotionVocabulary:
    """The motion-token vocabularies of the three agent types plus where they came from.

    ``method`` is "kdisks", "uniform_grid" or "reference" (the SMART authors' published file).
    Save and load with :mod:`.vocab_io` (``save_motion_vocabulary`` / ``load_motion_vocabulary``);
    :meth:`content_hash` is what checkpoints refer to.
    """

    types: Mapping[AgentType, TypeVocab]
    method: str = "kdisks"
    seed: int | None = None
    provenance: Mapping[str, Any] = field(default_factory=dict)

    def __getitem__(self, agent_type) -> TypeVocab:
        return self.types[AgentType(int(agent_type))]

    def sizes(self) -> dict[str, int]:
        return {AgentType(t).name.lower(): v.size for t, v in self.types.items()}

    def content_hash(self) -> str:
        return motion_vocabulary_hash(self)

    def stacked(self) -> tuple[np.ndarray, np.ndarray]:
        """(poses [4, Vmax, 6, 3], sizes [4]) indexed by AgentType (OTHER and missing types: size 0),
        padded with zero-motion tokens for batched lookup."""
        vmax = max(v.size for v in self.types.values())
        poses = np.zeros((len(AgentType), vmax, POSES_PER_TOKEN, 3), np.float32)
        sizes = np.zeros(len(AgentType), np.int64)
        for t, v in self.types.items():
            poses[int(t), : v.size] = v.poses
            sizes[int(t)] = v.size
        return poses, sizes


VOCABULARY_VERSION = 1
"""Version of the vocabulary format (files in :mod:`.vocab_io`); part of every content hash."""


def hash_arrays(header: str, arrays: list[tuple[str, np.ndarray]]) -> str:
    """SHA-256 (hex) of a header and named arrays (their dtype, shape and bytes)."""
    h = hashlib.sha256(header.encode())
    for name, a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{name}:{a.dtype.str}:{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def motion_vocabulary_hash(vocab: MotionVocabulary) -> str:
    """SHA-256 (hex) of the token poses and contours and the box sizes, per type in AgentType order
    (what checkpoints refer to a vocabulary by)."""
    arrays, boxes = [], []
    for t in sorted(vocab.types, key=int):
        v = vocab.types[t]
        arrays += [(f"{TYPE_KEYS[t]}.poses", v.poses.astype(np.float32)), (f"{TYPE_KEYS[t]}.contour", v.contour.astype(np.float32))]
        boxes.append(f"{TYPE_KEYS[t]}={v.length_m:.6f}x{v.width_m:.6f}")
    return hash_arrays(f"motion/v{VOCABULARY_VERSION}/" + ",".join(boxes), arrays)


# ------------------------------------------------------------------------------------ snippets
def snippets_from_tracks(position: np.ndarray, heading: np.ndarray, valid: np.ndarray, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Every fully valid 6-frame window of tracks ([N, T, 2+], [N, T], [N, T]) starting at frames
    0, stride, 2 * stride, ..., in the frame of its first pose.

    Returns (snippets [M, 6, 3] float32, track index of each [M]).
    """
    n, t = valid.shape
    if t < POSES_PER_TOKEN or n == 0:
        return np.zeros((0, POSES_PER_TOKEN, 3), np.float32), np.zeros(0, np.int64)
    poses = np.concatenate([np.asarray(position, np.float64)[..., :2], np.asarray(heading, np.float64)[..., None]], -1)
    starts = np.arange(0, t - POSES_PER_TOKEN + 1, stride)
    frames = starts[:, None] + np.arange(POSES_PER_TOKEN)  # [W, 6]
    win_valid = valid[:, frames].all(-1)  # [N, W]
    ti, wi = np.nonzero(win_valid)
    win = poses[ti[:, None], frames[wi]]  # [M, 6, 3]
    return relative_poses(win, win[:, :1]).astype(np.float32), ti.astype(np.int64)


def collect_snippets(scenarios: Iterable[Scenario], stride: int = 1) -> tuple[dict[AgentType, np.ndarray], dict[str, Any]]:
    """Snippets per motion type from scenes, plus provenance (scene ids, sources, counts)."""
    parts: dict[AgentType, list[np.ndarray]] = {t: [] for t in MOTION_TYPES}
    scenes = []
    for sc in scenarios:
        tr = sc.tracks
        snip, ti = snippets_from_tracks(tr.position, tr.heading, tr.valid, stride)
        counts = {}
        for t in MOTION_TYPES:
            sel = tr.types[ti] == t
            parts[t].append(snip[sel])
            counts[TYPE_KEYS[t]] = int(sel.sum())
        scenes.append({"scenario_id": sc.scenario_id, "source": sc.source,
                       "path": str(sc.metadata.get("path", sc.metadata.get("source_path", ""))), "snippets": counts})
    out = {t: (np.concatenate(p) if p else np.zeros((0, POSES_PER_TOKEN, 3), np.float32)) for t, p in parts.items()}
    provenance = {"scenes": scenes, "snippet_stride_frames": stride,
                  "snippets": {TYPE_KEYS[t]: int(len(v)) for t, v in out.items()}}
    return out, provenance


def augment_snippets(snippets: np.ndarray, count: int, rng: np.random.Generator, speed_jitter: float = 0.15,
                     yaw_rate_jitter_rad: float = 0.02, lateral_jitter_m: float = 0.02) -> np.ndarray:
    """``count`` new snippets made from random real ones: per-frame motion increments (in the
    previous pose's frame) scaled by a per-snippet speed factor ``1 + U(-j, j)``, heading increments
    and lateral increments jittered by Gaussian noise, then chained again. Used to reach a useful
    sample count from few scenes (and for the 1M-snippet speed check), never silently."""
    snippets = np.asarray(snippets, np.float64)
    if len(snippets) == 0:
        raise ValueError("cannot augment an empty set of snippets")
    src = snippets[rng.integers(0, len(snippets), count)]
    inc = relative_poses(src[:, 1:], src[:, :-1])  # [count, 5, 3] per-frame increments
    inc[..., 0] *= 1.0 + rng.uniform(-speed_jitter, speed_jitter, (count, 1))
    inc[..., 1] += rng.normal(0.0, lateral_jitter_m, inc.shape[:2]) * (np.abs(inc[..., 0]) > 0.05)
    inc[..., 2] += rng.normal(0.0, yaw_rate_jitter_rad, inc.shape[:2])
    out = np.zeros_like(src)
    for f in range(FRAMES_PER_TOKEN):
        out[:, f + 1] = compose_poses(out[:, f], inc[:, f])
    return out.astype(np.float32)


def build_motion_vocabulary(snippets: Mapping[AgentType, np.ndarray], sizes: int | Mapping[AgentType, int], seed: int = 0,
                            min_samples_per_token: int = 4, provenance: Mapping[str, Any] | None = None,
                            progress: bool = True, tolerance_m: float | Mapping[AgentType, float] | None = None) -> MotionVocabulary:
    """k-disks vocabularies per type from snippets [M, 6, 3] (see :func:`collect_snippets`).

    ``tolerance_m`` (per type or for all; None or 0: the covering radius is searched): a fixed disk
    radius, so that the tokens go to the dense motions first (:func:`~.kdisks.kdisks`).

    When a type has fewer than ``min_samples_per_token * size`` snippets, jittered copies
    (:func:`augment_snippets`) are added up to that count before clustering; the counts are recorded
    (``num_samples`` vs ``num_real_samples``). A type with no snippet at all is an error.
    """
    rng = np.random.default_rng(seed)
    types = {}
    for t in MOTION_TYPES:
        size = int(sizes[t] if isinstance(sizes, Mapping) else sizes)
        real = np.asarray(snippets.get(t, np.zeros((0, POSES_PER_TOKEN, 3))), np.float32)
        if len(real) == 0:
            warnings.warn(f"no {AgentType(t).name.lower()} snippets: the vocabulary has no {AgentType(t).name.lower()} tokens")
            continue
        samples = real
        want = min_samples_per_token * size
        if len(real) < want:
            samples = np.concatenate([real, augment_snippets(real, want - len(real), rng)])
        length, width = BOX_SIZE_M[t]
        contour = box_contour(samples, length, width).reshape(len(samples), -1, 2)
        tol = tolerance_m.get(t) if isinstance(tolerance_m, Mapping) else tolerance_m
        res = kdisks(contour, size, seed=int(rng.integers(2**31)), progress=progress, desc=f"k-disks {TYPE_KEYS[t]} {size}",
                     tolerance_m=tol or None)
        types[t] = TypeVocab.from_poses(samples[res.centre_indices], length, width, tolerance_m=res.tolerance_m,
                                        requested_size=size, num_samples=len(samples), num_real_samples=len(real))
    if not types:
        raise ValueError("no snippets of any motion type to build a vocabulary from")
    return MotionVocabulary(types=types, method="kdisks", seed=seed, provenance=dict(provenance or {}))


def _grid_bins(size: int) -> tuple[int, int, int]:
    """(nx, ny, nheading) with product ``size``: about half the bits to dx, a quarter to dy and heading."""
    p = int(round(math.log2(size)))
    if 2**p != size:
        raise ValueError(f"uniform grid sizes must be powers of two, got {size}")
    px = (p + 1) // 2
    py = (p - px) // 2
    return 2**px, 2**py, 2 ** (p - px - py)


def uniform_grid_vocabulary(snippets: Mapping[AgentType, np.ndarray], sizes: int | Mapping[AgentType, int],
                            provenance: Mapping[str, Any] | None = None, quantile: float = 0.005) -> MotionVocabulary:
    """The MotionLM-style baseline: a uniform grid over the end pose (dx, dy, dheading) of a snippet,
    spanning the data's [quantile, 1 - quantile] range per axis, cells at their centres; a token's
    intermediate poses are a linear interpolation from the start pose to the cell's pose (the
    grid quantizes only where the token ends). Same token count as k-disks."""
    types = {}
    for t in MOTION_TYPES:
        size = int(sizes[t] if isinstance(sizes, Mapping) else sizes)
        real = np.asarray(snippets[t], np.float64)
        end = real[:, -1]
        nbins = _grid_bins(size)
        axes = []
        for a, nb in enumerate(nbins):
            lo, hi = np.quantile(end[:, a], [quantile, 1 - quantile])
            if hi - lo < 1e-6:
                lo, hi = lo - 1e-3, hi + 1e-3
            step = (hi - lo) / nb
            axes.append(lo + step * (np.arange(nb) + 0.5))
        gx, gy, gh = np.meshgrid(*axes, indexing="ij")
        end_poses = np.stack([gx.ravel(), gy.ravel(), gh.ravel()], -1)  # [V, 3]
        frac = np.arange(POSES_PER_TOKEN) / FRAMES_PER_TOKEN
        poses = end_poses[:, None, :] * frac[None, :, None]
        length, width = BOX_SIZE_M[t]
        types[t] = TypeVocab.from_poses(poses, length, width, requested_size=size, num_samples=len(real),
                                        num_real_samples=len(real))
    prov = dict(provenance or {})
    prov["grid_bins"] = {TYPE_KEYS[t]: list(_grid_bins(types[t].size)) for t in MOTION_TYPES}
    return MotionVocabulary(types=types, method="uniform_grid", provenance=prov)


# -------------------------------------------------------------------------------- tokenization
@dataclass(frozen=True, eq=False)
class MotionTokens:
    """The motion tokens of ``N`` tracks over ``S`` token steps (the output of rolling matching)."""

    ids: np.ndarray  # [N, S] int64, token index in the track's type vocabulary (0 where invalid)
    valid: np.ndarray  # [N, S] bool, both boundary frames valid (and a motion type)
    start_pose: np.ndarray  # [N, S, 3] float32, the pose each token is placed at (reached or re-anchored)
    reached: np.ndarray  # [N, S + 1, 3] float32, the token sequence's pose at each boundary
    reached_valid: np.ndarray  # [N, S + 1] bool
    types: np.ndarray  # [N] int8, AgentType
    boundaries: np.ndarray  # [S + 1] int64, the frames of the token grid
    nearest_ids: np.ndarray  # [N, S] int64, the noise-free choice from the same start pose (== ids without noise)

    @property
    def num_steps(self) -> int:
        return int(self.ids.shape[1])


def _contour_torch(poses: torch.Tensor, length_m: float, width_m: float) -> torch.Tensor:
    c, s = poses[..., 2].cos(), poses[..., 2].sin()
    hl, hw = 0.5 * length_m, 0.5 * width_m
    lx = torch.tensor([hl, hl, -hl, -hl], dtype=poses.dtype)
    ly = torch.tensor([hw, -hw, -hw, hw], dtype=poses.dtype)
    x = poses[..., None, 0] + c[..., None] * lx - s[..., None] * ly
    y = poses[..., None, 1] + s[..., None] * lx + c[..., None] * ly
    return torch.stack([x, y], -1)


def tokenize_tracks(position: np.ndarray, heading: np.ndarray, valid: np.ndarray, types: np.ndarray,
                    vocab: MotionVocabulary, boundaries: np.ndarray, match: str = "contour", noise_topk: int = 0,
                    noise_prob: float = 1.0, rng: np.random.Generator | int | None = None,
                    agent_chunk: int = 64, candidates=None, relabel=None) -> MotionTokens:
    """Rolling matching of tracks ``position`` [N, T, 2+], ``heading`` [N, T], ``valid`` [N, T],
    ``types`` [N] on the token grid ``boundaries`` [S + 1] (see the module docstring).

    Vectorised over agents (per type, in chunks of ``agent_chunk`` against the whole vocabulary);
    the loop is over the S token steps, which depend on each other. Tracks of type OTHER get no
    valid token. Scenes can be batched by concatenating their tracks (same boundaries).

    ``candidates`` (closed-loop training, :mod:`smart_marl.catk`): a callable
    ``candidates(k, partial) -> allowed [N, Vmax] bool or None`` called before step ``k`` with the
    :class:`MotionTokens` filled up to step ``k - 1`` (later steps are zeros). Where a row of
    ``allowed`` has a true entry, token ``k`` is the closest to the track among the allowed tokens
    (no noise); ``nearest_ids`` stays the closest of the whole vocabulary, unless ``relabel``
    ``(k, nearest [N], ids [N], ok [N]) -> nearest [N]``, called after step ``k`` is chosen, says otherwise.
    """
    if match not in ("contour", "end"):
        raise ValueError(f"match must be 'contour' or 'end', got {match!r}")
    if not isinstance(rng, np.random.Generator):
        rng = np.random.default_rng(rng)
    boundaries = np.asarray(boundaries, np.int64)
    n = valid.shape[0]
    s = max(len(boundaries) - 1, 0)
    gt = np.concatenate([np.asarray(position, np.float64)[..., :2], np.asarray(heading, np.float64)[..., None]], -1)
    gt = np.where(np.asarray(valid)[..., None], np.nan_to_num(gt), 0.0)  # values on invalid frames are arbitrary
    types = np.asarray(types, np.int8)
    is_motion = np.isin(types, [int(t) for t in vocab.types])
    ids = np.zeros((n, s), np.int64)
    nearest = np.zeros((n, s), np.int64)
    tok_valid = np.zeros((n, s), bool)
    start = np.zeros((n, s, 3), np.float64)
    reached = np.zeros((n, s + 1, 3), np.float64)
    reached_valid = np.zeros((n, s + 1), bool)
    vocab_t = {t: (torch.from_numpy(np.ascontiguousarray(v.contour[:, 1:].reshape(v.size, -1, 2))), v) for t, v in vocab.types.items()}
    partial = MotionTokens(ids=ids, valid=tok_valid, start_pose=start, reached=reached, reached_valid=reached_valid,
                           types=types, boundaries=boundaries, nearest_ids=nearest)  # views of the arrays being filled
    for k in range(s):
        allowed = candidates(k, partial) if candidates is not None else None
        b0, b1 = int(boundaries[k]), int(boundaries[k + 1])
        frames = np.arange(b0 + 1, b1 + 1)
        ok = valid[:, b0] & valid[:, b1] & is_motion
        tok_valid[:, k] = ok
        carried = reached_valid[:, k] & ok  # previous token valid: roll from the reached pose
        start[:, k] = np.where(carried[:, None], reached[:, k], gt[:, b0])
        for t, (vc, v) in vocab_t.items():
            rows = np.flatnonzero(ok & (types == t))
            for c0 in range(0, len(rows), agent_chunk):
                r = rows[c0 : c0 + agent_chunk]
                target = relative_poses(gt[r][:, frames], start[r, k][:, None])  # [n, 5, 3]
                w = valid[r][:, frames].astype(np.float64)  # [n, 5]
                if match == "end":
                    w[:, :-1] = 0.0
                tc = _contour_torch(torch.from_numpy(target.astype(np.float32)), v.length_m, v.width_m)  # [n, 5, 4, 2]
                d = point_distance_matrices(tc.reshape(len(r), -1, 2), vc)  # [5 * 4, n, V] corner distances
                d = d.view(FRAMES_PER_TOKEN, 4, len(r), v.size).mean(1)  # [5, n, V] mean corner distance per frame
                wt = torch.from_numpy((w / w.sum(1, keepdims=True)).astype(np.float32))
                dist = (d * wt.t()[:, :, None]).sum(0)  # [n, V] mean corner distance over the valid frames
                best = dist.argmin(-1).numpy()
                choice = best.copy()
                if allowed is not None:
                    allow = torch.from_numpy(np.ascontiguousarray(allowed[r, : v.size]))
                    restricted = allow.any(-1).numpy()
                    closest_allowed = dist.masked_fill(~allow, float("inf")).argmin(-1).numpy()
                    choice = np.where(restricted, closest_allowed, best)
                elif noise_topk > 1:
                    kk = min(noise_topk, v.size)
                    top = torch.topk(dist, kk, dim=-1, largest=False).indices.numpy()  # [n, kk]
                    pick = top[np.arange(len(r)), rng.integers(0, kk, len(r))]
                    noisy = rng.random(len(r)) < noise_prob
                    choice = np.where(noisy, pick, best)
                ids[r, k] = choice
                nearest[r, k] = best
        if relabel is not None:
            nearest[:, k] = relabel(k, nearest[:, k].copy(), ids[:, k].copy(), ok)
        end_local = np.zeros((n, 3))
        for t, v in vocab.types.items():
            sel = ok & (types == t)
            end_local[sel] = v.poses[ids[sel, k], -1]
        # boundary k's pose: this token's start when valid, else what the previous token reached
        reached[:, k] = np.where(ok[:, None], start[:, k], reached[:, k])
        reached_valid[:, k] |= ok
        reached[:, k + 1] = np.where(ok[:, None], compose_poses(start[:, k], end_local), 0.0)
        reached_valid[:, k + 1] = ok
    return MotionTokens(ids=ids, valid=tok_valid, start_pose=start.astype(np.float32), reached=reached.astype(np.float32),
                        reached_valid=reached_valid, types=types, boundaries=boundaries, nearest_ids=nearest)


def tokenize_motion(scenario: Scenario, vocab: MotionVocabulary, **kwargs) -> MotionTokens:
    """Rolling matching of every track of a scene on its token grid (one row per track; tracks of
    type OTHER are all invalid). Keyword arguments go to :func:`tokenize_tracks`."""
    tr = scenario.tracks
    return tokenize_tracks(tr.position, tr.heading, tr.valid, tr.types, vocab,
                           token_boundaries(scenario.current_frame, scenario.num_frames), **kwargs)


# ------------------------------------------------------------------------------ detokenization
def _token_poses(ids: np.ndarray, types: np.ndarray, vocab: MotionVocabulary) -> np.ndarray:
    """Vocabulary poses [..., S, 6, 3] of token ids [..., S] for agents of ``types`` [...]."""
    table, sizes = vocab.stacked()
    ids = np.asarray(ids, np.int64)
    t = np.broadcast_to(np.asarray(types, np.int64)[..., None], ids.shape)
    if np.any((ids < 0) | (ids >= np.maximum(sizes[t], 1))):
        raise ValueError("token id outside its type's vocabulary")
    return table[t, ids]


def place_tokens(ids: np.ndarray, start_pose: np.ndarray, types: np.ndarray, vocab: MotionVocabulary) -> np.ndarray:
    """Each token's 6 poses placed at its own start pose: ids [..., S], start_pose [..., S, 3],
    types [...] -> [..., S, 6, 3]. (For re-anchored sequences, use :class:`MotionTokens.start_pose`.)"""
    local = _token_poses(ids, types, vocab)
    return compose_poses(np.asarray(start_pose, np.float64)[..., None, :], local.astype(np.float64)).astype(np.float32)


def detokenize(ids: np.ndarray, start_pose: np.ndarray, types: np.ndarray, vocab: MotionVocabulary) -> np.ndarray:
    """Token ids [..., S] chained from ``start_pose`` [..., 3] -> 10 Hz poses [..., 5 S + 1, 3].

    Batch dimensions ``...`` are free (agents, scenes, rollouts); ``types`` [...] picks each row's
    vocabulary. Each token starts where the previous one ended. Token validity is the caller's:
    every id is placed (for sequences with gaps, use :func:`reconstruct`).
    """
    local = _token_poses(ids, types, vocab).astype(np.float64)  # [..., S, 6, 3]
    s = local.shape[-3]
    pose = np.asarray(start_pose, np.float64)
    out = np.empty(local.shape[:-3] + (FRAMES_PER_TOKEN * s + 1, 3), np.float64)
    out[..., 0, :] = pose
    for k in range(s):
        placed = compose_poses(pose[..., None, :], local[..., k, 1:, :])  # [..., 5, 3]
        out[..., FRAMES_PER_TOKEN * k + 1 : FRAMES_PER_TOKEN * (k + 1) + 1, :] = placed
        pose = placed[..., -1, :]
    return out.astype(np.float32)


def reconstruct(tokens: MotionTokens, vocab: MotionVocabulary, num_frames: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Poses [N, T, 3] and their validity [N, T] rebuilt from tokens on the scene's frames: each
    valid token's poses placed at its start pose (the reached pose, or the ground truth where it
    re-anchored), covering frames b0 + 1 .. b1; anchors (frame b0 of a re-anchored token) are valid too."""
    b = tokens.boundaries
    t = int(num_frames if num_frames is not None else (b[-1] + 1 if len(b) else 0))
    n, s = tokens.ids.shape
    placed = place_tokens(tokens.ids, tokens.start_pose, tokens.types, vocab)  # [N, S, 6, 3]
    poses = np.zeros((n, t, 3), np.float32)
    out_valid = np.zeros((n, t), bool)
    for k in range(s):
        frames = np.arange(b[k], b[k] + POSES_PER_TOKEN)
        sel = tokens.valid[:, k]
        # frame b0 too: an anchor, or the pose the previous token ended at (the same when carried)
        poses[np.ix_(np.flatnonzero(sel), frames)] = placed[sel, k]
        out_valid[np.ix_(np.flatnonzero(sel), frames)] = True
    return poses, out_valid


# ------------------------------------------------------------------------- matching one move
PATH_HEADING_WEIGHT_M_PER_RAD = 2.0
"""How much a heading error counts against a position error when matching a path (m per rad)."""
PAIR_CHUNK = 32
"""First tokens whose pairs :func:`match_token_path`'s look-ahead scores together."""
PEDESTRIAN_PATH_HEADING_WEIGHT_M_PER_RAD = 1.0
"""Pedestrians turn on the spot and their headings are noisy in the data: heading counts half as much."""


def path_heading_weight(agent_type) -> float:
    """The heading weight :func:`match_token_path` uses for an agent type (m per rad)."""
    if int(agent_type) == int(AgentType.PEDESTRIAN):
        return PEDESTRIAN_PATH_HEADING_WEIGHT_M_PER_RAD
    return PATH_HEADING_WEIGHT_M_PER_RAD


def match_token_ends(end_poses: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The token whose end is nearest each target, per row: end_poses [V, 3] (one type's tokens'
    last poses, token start frame), target [M, 2] (a displacement in the agent's frame: the
    Euclidean distance decides) or [M, 3] (a displacement and a heading change: squared distance
    plus the squared wrapped heading difference, radians counted as metres) -> token ids [M]."""
    ends = np.asarray(end_poses, np.float64)
    target = np.asarray(target, np.float64)
    if target.shape[-1] == 2:
        return np.linalg.norm(target[:, None] - ends[None, :, :2], axis=-1).argmin(1)
    dh = wrap_angle(target[:, None, 2] - ends[None, :, 2])
    return (np.sum((target[:, None, :2] - ends[None, :, :2]) ** 2, -1) + dh ** 2).argmin(1)


def match_token_path(token_poses: torch.Tensor, vocab_size: int, current_pose: torch.Tensor, targets: torch.Tensor,
                     heading_weight: float = PATH_HEADING_WEIGHT_M_PER_RAD, allowed: torch.Tensor | None = None) -> torch.Tensor:
    """The token closest to a scripted motion, per row.

    token_poses [V, 6, 3] (one type's token poses in the token's start frame; rows beyond
    ``vocab_size`` are ignored), current_pose [M, 3] (where the token starts), targets [M, 5, 3]
    or [M, 10, 3] (the next 5 or 10 target poses, same frame as ``current_pose``) -> token ids [M]
    minimising the mean position error plus ``heading_weight`` x the mean heading error. With 10
    targets it looks one token ahead: the first token of the best *pair* of tokens (V^2 pairs), so
    that a token which is good now but leaves the agent badly oriented for the next one loses.
    ``allowed`` [M, >= vocab_size] bool: the first tokens each row may take (e.g. a policy's action
    space, the prior's top k; the second token of a pair is any), None: all.
    """
    poses = token_poses[:vocab_size, 1:].to(torch.float64)  # (V, 5, 3)
    cur = current_pose.to(torch.float64)
    tgt = targets.to(torch.float64)
    c, s = cur[:, 2].cos()[:, None], cur[:, 2].sin()[:, None]
    dx, dy = tgt[..., 0] - cur[:, None, 0], tgt[..., 1] - cur[:, None, 1]
    local = torch.stack([c * dx + s * dy, -s * dx + c * dy, tgt[..., 2] - cur[:, None, 2]], -1)  # (M, F, 3)

    def error(candidate: torch.Tensor, target: torch.Tensor) -> torch.Tensor:  # (..., F, 3) vs (M, 1.., F, 3)
        pos = (candidate[..., :2] - target[..., :2]).norm(dim=-1).mean(-1)
        dh = candidate[..., 2] - target[..., 2]
        return pos + heading_weight * wrap_angle(dh).abs().mean(-1)

    first = error(poses[None], local[:, None, :FRAMES_PER_TOKEN])  # (M, V)
    if allowed is not None:  # a first token not allowed is never scored: its pairs' bound is inf
        first = first.masked_fill(~allowed[:, :first.shape[1]].to(first.device), math.inf)
    if local.shape[1] < 2 * FRAMES_PER_TOKEN:
        return first.argmin(1)
    # pairs: token b placed at the end of token a. A pair's error is the mean of its first token's
    # error and its second's, so half the first token's error bounds every pair that starts with it:
    # first tokens are scored in chunks, best first, until none left unscored can reach the best pair
    # found. Unscored ones stay at inf, so the argmin (ties to the lowest id) is the full V x V one's.
    end = poses[:, -1]  # (V, 3)
    bx, by = poses[None, :, :, 0], poses[None, :, :, 1]
    order = first.argsort(1)  # (M, V) first tokens, best first
    if allowed is not None:  # only the allowed ones can be scored (the rest sort last, at inf)
        order = order[:, :max(int(torch.isfinite(first).sum(1).max()), 1)]
    pair_err = torch.full_like(first, math.inf)  # (M, V) each scored first token's best pair
    for lo in range(0, first.shape[1], PAIR_CHUNK):
        ids = order[:, lo:lo + PAIR_CHUNK]  # (M, C)
        rows = (first.gather(1, ids) / 2 <= pair_err.amin(1, keepdim=True)).any(1).nonzero().squeeze(1)
        if not len(rows):
            break
        ids = ids[rows]
        e = end[ids]  # (R, C, 3)
        c2, s2 = e[..., 2].cos()[..., None, None], e[..., 2].sin()[..., None, None]
        second = torch.stack([e[..., 0, None, None] + c2 * bx - s2 * by, e[..., 1, None, None] + s2 * bx + c2 * by,
                              e[..., 2, None, None] + poses[None, :, :, 2]], -1)  # (R, C, V, 5, 3)
        err2 = error(second, local[rows, None, None, FRAMES_PER_TOKEN: 2 * FRAMES_PER_TOKEN]).amin(2)  # (R, C)
        pair_err[rows] = pair_err[rows].scatter(1, ids, (first[rows].gather(1, ids) + err2) / 2)
    return pair_err.argmin(1)
