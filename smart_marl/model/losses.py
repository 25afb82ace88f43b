"""Model stage, training objective: next-token cross-entropies and accuracies.

* Motion: cross-entropy of the next motion token over every valid (agent, step) pair of every
  agent type, each type's rows through its own head over its own vocabulary.
* Road: cross-entropy of the next road token along road sequences: for each successor pair
  (piece i -> piece j) whose piece j is masked (its content hidden from RoadNet), predict j's token
  from i's encoding.
* Total = motion + road. Label smoothing is configurable (the reference uses 0.1).
* Optional speed-trend weights (:func:`speed_trend_weights`): every motion token of a vehicle
  counts with a weight chosen by what its own sequence does over the scene, speeding up, keeping its
  speed or slowing down, so that a training set whose traffic slows more than real traffic (SUMO's)
  can be reweighted toward real traffic's mix (a label-shift correction). Off by default.

Normalisation: each loss is a sum over target tokens divided by ``normaliser`` (by default the
batch's own count). Data-parallel training passes the count over all ranks times the world size,
so that the gradient DDP averages equals the gradient of one process on the union of the batches.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from ..scenario import AgentType
from ..tokens.motion import TOKEN_S
from .batch import SmartBatch
from .motionnet import NUM_MOTION_TYPES
from .smart import SMART

TYPE_NAMES = ("vehicle", "pedestrian", "cyclist")

TREND_NOW_STEP = 1  # the token that ends at the current frame (91-frame scenes whose current frame is 10)
TREND_LATE_STEPS = (16, 17)  # the two tokens that end 7.5 and 8 s after it
TREND_FAST_MPS = 5.0  # only vehicles faster than this now are weighted
TREND_BAND = 0.2  # late speed above (1 + band) x now: speeds up; below (1 - band) x now: slows; else keeps


def speed_trend_weights(batch: SmartBatch, weights: tuple[float, float, float]) -> torch.Tensor:
    """Per-agent loss weights [B, N]: ``weights`` = (speeds up, keeps its speed, slows) for the
    vehicles moving faster than :data:`TREND_FAST_MPS` at the current token whose mean speed over the
    tokens 7-8 s later is above 1.2x, within 20% of, or below 0.8x their speed now (token speeds from
    the poses the sequence reached, as in ``benchmarks/prior_speed_drift.py``'s ``late_by_log_trend``
    rows); 1 for every other agent and for batches without 8 s of tokens after the current one."""
    w = torch.ones(batch.agent_type.shape, device=batch.agent_pose.device)
    if batch.agent_pose.shape[2] <= max(TREND_LATE_STEPS):
        return w
    step_m = (batch.agent_pose[..., :2] - batch.agent_start_pose[..., :2]).float().norm(dim=-1)  # [B, N, S]
    late = list(TREND_LATE_STEPS)
    now_mps = step_m[:, :, TREND_NOW_STEP] / TOKEN_S
    late_mps = step_m[:, :, late].mean(-1) / TOKEN_S
    ok = ((batch.agent_type == int(AgentType.VEHICLE)) & (now_mps > TREND_FAST_MPS)
          & batch.agent_valid[:, :, TREND_NOW_STEP] & batch.agent_valid[:, :, late].all(-1))
    ratio = late_mps / now_mps.clamp(min=1e-6)
    up, slow = ok & (ratio > 1.0 + TREND_BAND), ok & (ratio < 1.0 - TREND_BAND)
    w[up], w[ok & ~up & ~slow], w[slow] = (float(x) for x in weights)
    return w


def rows_reaching_targets(batch: SmartBatch) -> torch.Tensor:
    """The valid (agent, step) rows [B, N, S] whose features can reach a next-token target: those at
    steps up to the last step of their scene that has a target. A step's features depend only on its
    own and earlier steps (temporal attention is causal) and on the other agents at the same step, so
    the rows after the last target (the final token step of a log, whose next token is unknown) cannot
    change the loss and are not computed."""
    steps = torch.arange(batch.target_valid.shape[2], device=batch.target_valid.device)
    has_target = batch.target_valid.any(1)  # (B, S)
    last = torch.where(has_target, steps, torch.full_like(steps, -1)).max(1).values  # (B,) -1: no target at all
    return batch.agent_valid & (steps[None, None, :] <= last[:, None, None])


def road_target_pairs(batch: SmartBatch) -> tuple[torch.Tensor, torch.Tensor]:
    """The road next-token task's pairs: successor pairs (piece i -> piece j) along the lanes whose j is
    masked (its content hidden from RoadNet) and whose i is not; j's token is predicted from i's
    encoding. Returns (i, j) [M] as rows of the flat B*R road table."""
    b, r = batch.road_valid.shape
    flat = batch.road_pairs + (torch.arange(b, device=batch.road_pairs.device) * r)[:, None, None]  # (B, E, 2)
    masked = batch.road_masked.reshape(-1)
    ok = batch.road_pair_valid & masked[flat[..., 1]] & ~masked[flat[..., 0]]  # (B, E)
    return flat[..., 0][ok], flat[..., 1][ok]


class NextTokenLoss(nn.Module):
    """Wraps :class:`SMART` so that one ``forward`` gives the losses (what DDP wraps)."""

    def __init__(self, model: SMART, label_smoothing: float = 0.1,
                 trend_weights: tuple[float, float, float] | None = None) -> None:
        super().__init__()
        self.model = model
        self.label_smoothing = float(label_smoothing)
        self.trend_weights = tuple(trend_weights) if trend_weights is not None else None

    def forward(self, batch: SmartBatch, motion_normaliser: torch.Tensor | float | None = None,
                road_normaliser: torch.Tensor | float | None = None) -> dict[str, torch.Tensor]:
        """Returns ``loss`` (motion + road, differentiable), ``motion_loss``, ``road_loss`` and
        detached counts for metrics: ``{type}_tokens``, ``{type}_top1``, ``{type}_top5`` (numbers of
        correct predictions), ``road_tokens``, ``road_top1``. With ``trend_weights`` each motion
        token's cross-entropy is multiplied by its agent's :func:`speed_trend_weights` (the
        normaliser stays the token count)."""
        src, dst = road_target_pairs(batch)  # rows of the B*R road table
        road_read = torch.zeros(batch.road_valid.numel(), dtype=torch.bool, device=src.device).index_fill_(0, src, True)
        feats, road_x = self.model(batch, road_masked=batch.road_masked, agent_valid=rows_reaching_targets(batch),
                                   road_read=road_read.view_as(batch.road_valid))  # (B, N, S, d), (B, R, d)
        agent_w = speed_trend_weights(batch, self.trend_weights) if self.trend_weights is not None else None
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
            if agent_w is None:
                motion_sum = motion_sum + F.cross_entropy(logits, target, reduction="sum", label_smoothing=self.label_smoothing)
            else:
                ce = F.cross_entropy(logits, target, reduction="none", label_smoothing=self.label_smoothing)
                motion_sum = motion_sum + (ce * agent_w[:, :, None].expand_as(sel)[sel]).sum()
            n_motion = n_motion + target.numel()
            out.update(_accuracy_counts(TYPE_NAMES[t], logits.detach(), target))
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
