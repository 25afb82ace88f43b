"""Model stage, training objective: next-token cross-entropies and accuracies.

* Motion: cross-entropy of the next motion token over every valid (agent, step) pair of every
  agent type, each type's rows through its own head over its own vocabulary.
* Road: cross-entropy of the next road token along road sequences: for each successor pair
  (piece i -> piece j) whose piece j is masked (its content hidden from RoadNet), predict j's token
  from i's encoding.
* Total = motion + road. Label smoothing is configurable (the reference uses 0.1).

Normalisation: each loss is a sum over target tokens divided by ``normaliser`` (by default the
batch's own count). Data-parallel training passes the count over all ranks times the world size,
so that the gradient DDP averages equals the gradient of one process on the union of the batches.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from .batch import SmartBatch
from .motionnet import NUM_MOTION_TYPES
from .smart import SMART

TYPE_NAMES = ("vehicle", "pedestrian", "cyclist")


class NextTokenLoss(nn.Module):
    """Wraps :class:`SMART` so that one ``forward`` gives the losses (what DDP wraps)."""

    def __init__(self, model: SMART, label_smoothing: float = 0.1) -> None:
        super().__init__()
        self.model = model
        self.label_smoothing = float(label_smoothing)

    def forward(self, batch: SmartBatch, motion_normaliser: torch.Tensor | float | None = None,
                road_normaliser: torch.Tensor | float | None = None) -> dict[str, torch.Tensor]:
        """Returns ``loss`` (motion + road, differentiable), ``motion_loss``, ``road_loss`` and
        detached counts for metrics: ``{type}_tokens``, ``{type}_top1``, ``{type}_top5`` (numbers of
        correct predictions), ``road_tokens``, ``road_top1``."""
        feats, road_x = self.model(batch, road_masked=batch.road_masked)  # (B, N, S, d), (B, R, d)
        d = feats.shape[-1]
        out: dict[str, torch.Tensor] = {}
        motion_sum = feats.new_zeros(())
        n_motion = feats.new_zeros(())
        tv = batch.target_valid
        for t in range(NUM_MOTION_TYPES):
            sel = tv & (batch.agent_type == t)[:, :, None]  # (B, N, S)
            x = feats[sel]  # (M_t, d); empty rows still take part in the graph (DDP sees every head used)
            logits = self.model.motion_heads[t](x).float()  # (M_t, V_t)
            target = batch.target_tokens[sel]
            motion_sum = motion_sum + F.cross_entropy(logits, target, reduction="sum", label_smoothing=self.label_smoothing)
            n_motion = n_motion + target.numel()
            out.update(_accuracy_counts(TYPE_NAMES[t], logits.detach(), target))
        # road next token: pairs (i -> j) with j masked, i not masked
        b, e = batch.road_pairs.shape[:2]
        r = road_x.shape[1]
        flat = batch.road_pairs + (torch.arange(b, device=road_x.device) * r)[:, None, None]  # (B, E, 2) rows of (B*R)
        masked = batch.road_masked.reshape(-1)
        ok = batch.road_pair_valid & masked[flat[..., 1]] & ~masked[flat[..., 0]]  # (B, E)
        src, dst = flat[..., 0][ok], flat[..., 1][ok]
        road_logits = self.model.road_head(road_x.reshape(-1, d)[src]).float()  # (M_r, V_road)
        road_target = batch.road_token.reshape(-1)[dst]
        road_sum = F.cross_entropy(road_logits, road_target, reduction="sum", label_smoothing=self.label_smoothing)
        out.update(_accuracy_counts("road", road_logits.detach(), road_target, top5=False))
        mnorm = motion_normaliser if motion_normaliser is not None else n_motion.clamp(min=1)
        rnorm = road_normaliser if road_normaliser is not None else max(road_target.numel(), 1)
        out["motion_loss"] = motion_sum / mnorm
        out["road_loss"] = road_sum / rnorm
        out["loss"] = out["motion_loss"] + out["road_loss"]
        return out


def _accuracy_counts(name: str, logits: torch.Tensor, target: torch.Tensor, top5: bool = True) -> dict[str, torch.Tensor]:
    out = {f"{name}_tokens": torch.tensor(float(target.numel()), device=logits.device)}
    if target.numel() == 0:
        out[f"{name}_top1"] = torch.zeros((), device=logits.device)
        if top5:
            out[f"{name}_top5"] = torch.zeros((), device=logits.device)
        return out
    out[f"{name}_top1"] = (logits.argmax(-1) == target).sum().float()
    if top5:
        k = min(5, logits.shape[-1])
        out[f"{name}_top5"] = (logits.topk(k, -1).indices == target[:, None]).any(-1).sum().float()
    return out


def summarise(counts: dict[str, float]) -> dict[str, float]:
    """Accuracy figures from summed counts: ``{type}_top1_acc``, ``{type}_top5_acc``, overall
    ``motion_top1_acc``/``motion_top5_acc`` and ``road_top1_acc`` (NaN where no token)."""
    out = {}
    tot = {"top1": 0.0, "top5": 0.0, "tokens": 0.0}
    for name in TYPE_NAMES + ("road",):
        n = counts.get(f"{name}_tokens", 0.0)
        for k in ("top1", "top5"):
            if f"{name}_{k}" in counts:
                out[f"{name}_{k}_acc"] = counts[f"{name}_{k}"] / n if n else float("nan")
                if name != "road":
                    tot[k] += counts[f"{name}_{k}"]
        if name != "road":
            tot["tokens"] += n
    for k in ("top1", "top5"):
        out[f"motion_{k}_acc"] = tot[k] / tot["tokens"] if tot["tokens"] else float("nan")
    return out
