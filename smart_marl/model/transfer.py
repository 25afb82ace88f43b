"""Start a model on a new motion vocabulary from a trained one (warm start across vocabularies).

Everything in SMART except the last layer of each motion head is vocabulary-free: a token enters
the model through ``token_mlp`` applied to its contour, so a new vocabulary's tokens get sensible
input embeddings from the old weights. The head's last layer has one row (and bias) per token; a
new token takes the row of the old token whose contour is nearest (mean corner distance, metres),
its bias lowered by ``log(n)`` when ``n`` new tokens share that old token, so the probability the
old model gave a motion is split among the new tokens near it instead of multiplied.
"""

from __future__ import annotations

import dataclasses

import torch

from ..errors import SmartMarlError
from ..scenario import AgentType
from ..tokens import MotionVocabulary
from ..tokens.motion import MOTION_TYPES
from .checkpoint import Checkpoint
from .smart import SMART


class TransferError(SmartMarlError, ValueError):
    """A motion vocabulary a checkpoint cannot be moved onto (a type without tokens, an unknown type)."""


def nearest_tokens(old_contour: torch.Tensor, new_contour: torch.Tensor) -> torch.Tensor:
    """old [Vo, 6, 4, 2], new [Vn, 6, 4, 2] contours (metres) -> [Vn] index of the nearest old token
    by mean corner distance over the 6 poses x 4 corners."""
    old = old_contour.reshape(old_contour.shape[0], -1, 2)  # (Vo, 24, 2)
    new = new_contour.reshape(new_contour.shape[0], -1, 2)  # (Vn, 24, 2)
    dist = (new[:, None] - old[None]).norm(dim=-1).mean(-1)  # (Vn, Vo)
    return dist.argmin(dim=1)


def merge_vocabularies(base: MotionVocabulary, new: MotionVocabulary, types) -> MotionVocabulary:
    """``base`` with the agent ``types`` (AgentType values or names, e.g. "pedestrian") taken from ``new``."""
    try:
        chosen = {AgentType[t.upper()] if isinstance(t, str) else AgentType(int(t)) for t in types}
    except (KeyError, ValueError, TypeError) as exc:
        raise TransferError(f"types: {list(types)!r} are not all agent types (vehicle, pedestrian, cyclist)") from exc
    missing = sorted(t.name.lower() for t in chosen if t not in new.types or new.types[t].size < 1)
    if missing:
        raise TransferError(f"the new motion vocabulary has no tokens for {', '.join(missing)}")
    merged = {t: (new.types[t] if t in chosen else v) for t, v in base.types.items()}
    merged.update({t: new.types[t] for t in chosen if t not in merged})
    summary = {k: v for k, v in new.provenance.items() if k != "scenes"}  # the base keeps its own scene list
    if "scenes" in new.provenance:
        summary["num_scenes"] = len(new.provenance["scenes"])
    provenance = {**base.provenance, "merged": {t.name.lower(): summary for t in sorted(chosen)}}
    return MotionVocabulary(types=merged, method=base.method, seed=base.seed, provenance=provenance)


@torch.no_grad()
def transfer_motion_vocabulary(ck: Checkpoint, motion_vocab: MotionVocabulary, types=None) -> Checkpoint:
    """A copy of ``ck`` that speaks ``motion_vocab``: same weights, contours from the new vocabulary,
    each motion head's last layer re-indexed by :func:`nearest_tokens` (see the module docstring).
    ``types`` (e.g. ``["pedestrian"]``): only those agent types move to the new vocabulary, the others
    keep the checkpoint's tokens and head rows exactly. The road vocabulary is kept.
    ``meta['transferred_from']`` records the source checkpoint."""
    if types is not None:
        motion_vocab = merge_vocabularies(ck.motion_vocab, motion_vocab, types)
    missing = [t.name.lower() for t in MOTION_TYPES if t not in motion_vocab.types or motion_vocab.types[t].size < 1]
    other = [AgentType(t).name.lower() for t in motion_vocab.types if t not in MOTION_TYPES]
    if missing or other:
        raise TransferError(f"the motion vocabulary has no tokens for {', '.join(missing)}: the model needs tokens of every "
                            f"motion type (pass --types with the types it has)" if missing else
                            f"the motion vocabulary holds tokens of {', '.join(other)}, which no motion head speaks")
    sizes = tuple(motion_vocab[t].size for t in range(len(ck.model.motion_contours)))
    config = dataclasses.replace(ck.model.config, motion_vocab_sizes=sizes)
    new_contours = [torch.as_tensor(motion_vocab[t].contour, dtype=torch.float32) for t in range(len(sizes))]
    model = SMART(config, new_contours)
    old_state = ck.model.state_dict()
    state = model.state_dict()
    for t, (old_c, new_c) in enumerate(zip(ck.model.motion_contours, new_contours)):
        if motion_vocab[t] is ck.motion_vocab[t]:  # a type that keeps its vocabulary keeps its head exactly
            continue
        pick = nearest_tokens(old_c.float().cpu(), new_c)
        shared = torch.bincount(pick, minlength=old_c.shape[0]).float()
        last = len(model.motion_heads[t]) - 1
        w, b = f"motion_heads.{t}.{last}.weight", f"motion_heads.{t}.{last}.bias"
        old_state[w] = old_state[w][pick]
        old_state[b] = old_state[b][pick] - shared[pick].log()
        old_state[f"motion_contour_{t}"] = state[f"motion_contour_{t}"]
    model.load_state_dict(old_state)
    meta = {**ck.meta, "transferred_from": str(ck.path) if ck.path else "(in memory)"}
    return Checkpoint(model=model, motion_vocab=motion_vocab, road_vocab=ck.road_vocab, meta=meta, path=None)
