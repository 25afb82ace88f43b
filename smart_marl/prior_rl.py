"""Training stage, the prior fine-tuned by its own reinforcement learning (issue 33).

Next-token training never shows the prior what its own draws lead to: its logs are drives in which
nobody ran into anybody, and a follower whose leader brakes harder than in any log has no target that
says "brake more". This stage rolls the prior out on training scenes in which some leaders brake hard,
scores what each simulated agent's draws led to, and moves the weights toward the draws that kept
their distance (policy gradient with a group baseline, KL-regularised toward the weights it started
from, as the issue's SPACeR / SMART-R1 suggestion):

1. ``scenes_per_iteration`` training scenes; in each, a share of the leaders that have a follower
   brake from an onset at 4-9 m/s2 (:func:`smart_marl.braking.braking_leaders`); those leaders follow
   the edited log (scripted), every other agent is the prior's.
2. ``rollouts`` sampled rollouts of each scene under the current weights, all scenes and rollouts
   stepped together (:func:`smart_marl.catk.sampled_tokens`: top-k sampling as the simulator draws).
3. Each simulated agent's return: ``-1`` if it runs into another agent (its first rounded-box overlap
   with another present agent, the other within 45 degrees of its heading a frame before: it hit the
   other with its front; :func:`at_fault_collisions`) or, a vehicle on the road at the current frame,
   leaves the road (``offroad``, :func:`first_offroad`), else 0; with ``progress`` > 0, minus that times how far
   the distance it drove is from its logged distance (:func:`progress_error`); vehicles within
   ``progress_queue_m`` behind a braking leader in its lane are not judged on progress (their log did not brake).
   With ``discount`` < 1 the penalty is a reward at the step it happens: the token drawn n steps before
   it sees ``-discount**n`` (the return from that step on), so blame falls on the last seconds before a
   collision rather than on the whole drive.
4. Its advantage at each token step: that return minus the mean return of the same agent at that step over
   the scene's rollouts (a group baseline, no critic), on every token it drew up to that collision.
5. Loss: ``-mean(A * log pi(token)) + beta * mean KL(pi || pi_ref)`` over the drawn tokens of the
   simulated agents (:func:`rl_loss`), ``pi_ref`` the frozen starting weights.

``objective="rule"`` teaches the weights the simulator's collision rule instead (:func:`rule_loss`): the same
sampled rollouts, drawn plainly, record at every step the tokens the rule would not have let each agent draw
(:func:`smart_marl.catk.sampled_tokens`, ``excluded``), and the loss is the KL from the starting weights' distribution
with those tokens taken out (what the rule would draw from) to the current one; no reward, no baseline.

What comes in: a checkpoint (or ``"embedded"``) and training scenes. What goes out: checkpoints of the
fine-tuned prior and a JSON-lines log (``train.jsonl``: per iteration the share of simulated agents at
fault in a collision, the KL, the loss) in ``out_dir``. CPU or one GPU; resumable from ``last``.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from .braking import behind_in_lane, braking_leaders, with_braking_leaders
from .catk import _agent_shapes, first_future_step, sampled_tokens
from .geometry import bearing_deg, box_distance_to_road_edge, first_overlaps
from .geometry_torch import scene_road_edges
from .model.batch import SmartBatch, collate_scenes, scene_road, scene_tensors
from .model.checkpoint import checkpoint_paths, load_checkpoint, load_embedded, save_checkpoint
from .model.losses import rows_reaching_targets
from .model.motionnet import NUM_MOTION_TYPES
from .rollout import DEFAULT_TOP_K
from .rollout.frames import token_frames
from .scenario import AgentType, Scenario
from .tokens import FRAMES_PER_TOKEN, MotionTokens, MotionVocabulary
from .train_data import open_scenes

AT_FAULT_DEG = 45.0  # the other agent within this angle of the agent's heading: it ran into the other


@dataclass
class PriorRLConfig:
    """Every knob of a run (module docstring)."""

    scenes: str = "data/rl_train"  # training scenes: a scene cache folder, scene files, a folder or a glob
    out_dir: str = "runs/prior_rl"
    init: str = "embedded"  # the checkpoint to start from (and the KL reference)
    iterations: int = 100
    scenes_per_iteration: int = 4
    rollouts: int = 8  # per scene: the group of the baseline
    top_k: int = DEFAULT_TOP_K
    brake_share: float = 0.5  # share of each scene's leaders that brake hard
    offroad: bool = True  # a vehicle on the road now that leaves it is penalised as a collision is
    progress: float = 0.0  # weight of the progress term: -progress * |distance driven / logged distance - 1| (capped at 1)
    progress_queue_m: float = 0.0  # vehicles this far behind a braking leader in its lane are not judged on progress
    discount: float = 1.0  # per token step: a penalty reaches the token drawn n steps before it times discount**n
    objective: str = "rl"  # "rl": the policy gradient above; "rule": the collision rule taught to the weights (rule_loss)
    rule_anchor: float = 1.0  # "rule": the weight of the rows where the rule excludes nothing (KL to the starting weights)
    rule_offroad: bool = False  # "rule": tokens that end a vehicle on the road off it are excluded too (the shield's test)
    lr: float = 3e-5
    beta: float = 0.1  # weight of KL(pi || pi_ref)
    grad_clip: float = 1.0
    save_every: int = 10
    seed: int = 0
    threads: int = 0  # torch threads (0: torch's default)


# ------------------------------------------------------------------------------ rewards
def token_step_frames(tokens: MotionTokens, vocab: MotionVocabulary, first_step: int) -> tuple[np.ndarray, np.ndarray]:
    """(poses [N, F, 3], present [N, F]) of every track over the frames of token steps ``first_step``
    onward (5 per step: the token's contour poses placed where it starts), F = 5 x those steps."""
    n, s = tokens.ids.shape
    steps = max(s - first_step, 0)
    local = np.zeros((n, steps, FRAMES_PER_TOKEN + 1, 3), np.float32)
    for t, v in vocab.types.items():
        rows = np.flatnonzero(tokens.types == int(t))
        if len(rows):
            local[rows] = v.poses[tokens.ids[rows, first_step:]]
    start = torch.from_numpy(tokens.start_pose[:, first_step:]).float()
    poses = token_frames(torch.from_numpy(local), start, start, interpolation="contour").numpy()
    present = np.repeat(tokens.valid[:, first_step:], FRAMES_PER_TOKEN, axis=1)
    return poses.reshape(n, steps * FRAMES_PER_TOKEN, 3), present


def at_fault_collisions(poses: np.ndarray, present: np.ndarray, size: np.ndarray) -> np.ndarray:
    """int [N]: for each track, the frame of its first collision in which it ran into the other (its
    rounded box overlaps another present track's, :func:`smart_marl.geometry.first_overlaps`, and that
    track's centre was within :data:`AT_FAULT_DEG` of its heading a frame before), -1 where none.
    poses [N, F, 3], present [N, F], size [N, 2+] (length, width)."""
    first, partners = first_overlaps(poses, present, size[:, 0], size[:, 1])
    out = np.full(len(first), -1, np.int64)
    for i in np.flatnonzero(first >= 0):
        before = max(int(first[i]) - 1, 0)
        for j in partners[i]:
            d = poses[j, before, :2] - poses[i, before, :2]
            if bearing_deg(float(d[0]), float(d[1]), float(poses[i, before, 2])) < AT_FAULT_DEG:
                out[i] = first[i]
                break
    return out


def first_offroad(poses: np.ndarray, present: np.ndarray, size: np.ndarray, z: np.ndarray, segments, rows: np.ndarray) -> np.ndarray:
    """int [N]: for tracks ``rows``, the first frame where their box leaves the road (the metrics' test:
    a bottom corner beyond the road edge, :func:`smart_marl.geometry.box_distance_to_road_edge`), -1 where
    none or for the other tracks. poses [N, F, 3], present [N, F], size [N, 3], z [N] (held)."""
    out = np.full(len(present), -1, np.int64)
    if segments is None or not len(rows):
        return out
    p = poses[rows].astype(np.float64)
    zz = np.broadcast_to(z[rows, None], p.shape[:2])
    sz = [np.broadcast_to(size[rows, i, None], p.shape[:2]) for i in range(3)]
    off = (box_distance_to_road_edge(p[..., 0], p[..., 1], zz, sz[0], sz[1], sz[2], p[..., 2], segments) > 0) & present[rows]
    hit = off.any(1)
    out[rows[hit]] = off[hit].argmax(1)
    return out


def progress_error(scene: Scenario, tokens: MotionTokens, first_step: int, min_log_m: float = 5.0) -> np.ndarray:
    """float [N]: ``|distance driven / logged distance - 1|``, capped at 1, of each track over its drawn tokens
    (steps ``first_step`` on; the same token spans in the log), 0 for tracks whose log covers less than
    ``min_log_m`` there. A prior that avoids collisions by crawling loses here what it gains there."""
    v = tokens.valid[:, first_step:]
    b = tokens.boundaries
    driven = np.linalg.norm(np.diff(tokens.reached[:, first_step:, :2], axis=1), axis=-1)  # [N, S - first_step]
    pos = scene.tracks.position[:, b[first_step:], :2]
    logged = np.linalg.norm(np.diff(pos, axis=1), axis=-1)
    d, l = (driven * v).sum(1), (logged * v).sum(1)
    moving = l >= min_log_m
    return np.where(moving, np.minimum(np.abs(d / np.maximum(l, 1e-6) - 1.0), 1.0), 0.0)


# ------------------------------------------------------------------------------ the losses
def _log_probs_by_type(model, reference, batch: SmartBatch):
    """Per motion type with rows: (sel [B, N, S] the rows of ``batch`` with a valid target of that type,
    log pi [M_t, V_t], log pi_ref [M_t, V_t] (no gradient)), ``reference`` the frozen model."""
    rows = rows_reaching_targets(batch)
    feats, _ = model(batch, agent_valid=rows)
    with torch.no_grad():
        ref_feats, _ = reference(batch, agent_valid=rows)
    for t in range(NUM_MOTION_TYPES):
        sel = batch.target_valid & (batch.agent_type == t)[:, :, None]
        if not sel.any():
            continue
        logp = F.log_softmax(model.motion_heads[t](feats[sel]).float(), -1)
        with torch.no_grad():
            ref_logp = F.log_softmax(reference.motion_heads[t](ref_feats[sel]).float(), -1)
        yield sel, logp, ref_logp


def rl_loss(model, reference, batch: SmartBatch, weight: torch.Tensor, beta: float, total: int | None = None) -> dict[str, torch.Tensor]:
    """``-sum(weight * log pi(target)) / M + beta * sum KL(pi || pi_ref) / M`` over the M (agent, step)
    rows of ``batch`` with a valid target (the token drawn next), ``weight`` [B, N, S] the advantages of
    those rows; ``reference`` the frozen model of the KL; ``total`` replaces M (a part of a larger batch whose
    gradients are summed: the whole batch's M). Returns ``loss`` and detached ``pg``, ``kl``."""
    pg = kl = torch.zeros(())
    count = 0
    for sel, logp, ref_logp in _log_probs_by_type(model, reference, batch):
        taken = logp.gather(1, batch.target_tokens[sel][:, None])[:, 0]
        pg = pg - (weight[sel] * taken).sum()
        kl = kl + (logp.exp() * (logp - ref_logp)).sum()
        count += int(sel.sum())
    m = max(count if total is None else total, 1)
    loss = (pg + beta * kl) / m
    return {"loss": loss, "pg": pg.detach() / m, "kl": kl.detach() / m, "tokens": torch.tensor(float(count))}


def rule_loss(model, reference, batch: SmartBatch, excluded: torch.Tensor, total: int | None = None,
              anchor: float = 1.0) -> dict[str, torch.Tensor]:
    """The collision rule taught to the weights: ``sum w KL(q || pi) / M`` over the M rows of ``batch`` with a
    valid target, ``q`` the reference's distribution with the tokens the rule excluded there (``excluded``
    [B, N, S, Vmax] bool) taken out and the rest renormalised: the reference's draw under the rule. Where
    nothing is excluded ``q`` is the reference's own and the row weighs ``anchor`` (it holds the weights there;
    the rule touches about 1% of the rows, so at 1 they outweigh what it teaches), elsewhere 1; where everything
    is excluded, the row is left out. Returns ``loss``, detached ``kl`` (unweighted) and ``excluded_mass`` (pi's
    mean probability on excluded tokens over the rows it is taught on), ``ruled`` (their number), ``tokens``."""
    kl = loss = torch.zeros(())
    mass, ruled, count = 0.0, 0, 0
    for sel, logp, ref_logp in _log_probs_by_type(model, reference, batch):
        out = excluded[sel][:, : logp.shape[1]]
        keep = ~out.all(-1)
        log_q = torch.log_softmax(ref_logp.masked_fill(out, float("-inf")), -1)[keep]
        row_kl = (log_q.exp() * (log_q.clamp(min=-1e4) - logp[keep])).sum(-1)
        kl = kl + row_kl.sum()
        loss = loss + torch.where(out[keep].any(-1), 1.0, anchor) @ row_kl
        hit = out.any(-1) & keep
        mass += float((logp.detach().exp() * out).sum(-1)[hit].sum())
        ruled, count = ruled + int(hit.sum()), count + int(sel.sum())
    m = max(count if total is None else total, 1)
    return {"loss": loss / m, "kl": kl.detach() / m, "excluded_mass": torch.tensor(mass / max(ruled, 1)),
            "ruled": torch.tensor(float(ruled)), "tokens": torch.tensor(float(count))}


# ------------------------------------------------------------------------------ one iteration
def scene_batch(scenes: Sequence[Scenario], tokens: Sequence[MotionTokens], roads, vocab: MotionVocabulary,
                advantage: Sequence[np.ndarray], last_step: Sequence[np.ndarray], scripted: Sequence[np.ndarray],
                first_step: int) -> tuple[SmartBatch, torch.Tensor]:
    """The training batch of sampled rollouts (targets: the drawn tokens) and its weights [B, N, S, ...]:
    track ``r``'s advantage ([N], or [N, S] per token step, or [N, S, V]: per token step and token, e.g. the
    rule's excluded tokens) on the tokens it drew from ``first_step`` to ``last_step[r]``; scripted
    tracks and the history are no target (zero)."""
    arrays, weights = [], []
    for sc, mt, road, adv, last, scr in zip(scenes, tokens, roads, advantage, last_step, scripted):
        drawn = dataclasses.replace(mt, nearest_ids=mt.ids)
        a = scene_tensors(sc, vocab, road, road_mask_prob=0.0, motion_tokens=drawn)
        keep = np.flatnonzero(mt.valid.any(1))
        steps = np.arange(mt.ids.shape[1])
        target = (steps[None, :] >= first_step) & (steps[None, :] <= last[keep, None]) & ~scr[keep, None]
        tv = a["target_valid"].copy()
        tv[:, :-1] &= target[:, 1:]
        tv[:, -1] = False
        w = np.zeros(tv.shape + adv.shape[2:], adv.dtype if adv.ndim > 2 else np.float32)
        w[:, :-1] = adv[keep, None] if adv.ndim == 1 else adv[keep, 1:]
        arrays.append({**a, "target_valid": tv})
        weights.append(w * tv.reshape(tv.shape + (1,) * (w.ndim - 2)))
    batch = collate_scenes(arrays)
    wt = torch.zeros(batch.target_valid.shape + weights[0].shape[2:], dtype=torch.from_numpy(weights[0]).dtype)
    for i, w in enumerate(weights):
        wt[i, : w.shape[0], : w.shape[1]] = torch.from_numpy(w)
    return batch, wt


def rollout_group(model, scene: Scenario, road, vocab: MotionVocabulary, cfg: PriorRLConfig, rng: np.random.Generator,
                  generator: torch.Generator):
    """One scene with braking leaders, ``cfg.rollouts`` sampled rollouts of it, their at-fault collisions.
    Returns (scenes, tokens, roads, advantages [K, N, S], last steps [K, N], scripted [N], the shares of
    the simulated agent-rollouts penalised, at fault in a collision, off the road, and their mean progress error)."""
    edits = braking_leaders(scene, rng, cfg.brake_share)
    edited = with_braking_leaders(scene, edits)
    scripted = np.zeros(scene.num_tracks, bool)
    scripted[[e[0] for e in edits]] = True
    k = cfg.rollouts
    rule: dict | None = {} if cfg.objective == "rule" else None
    tokens = sampled_tokens(model, [edited] * k, [road] * k, vocab, cfg.top_k, generator, [scripted] * k, excluded=rule,
                            offroad=cfg.rule_offroad)
    kc = first_future_step(scene)
    size = _agent_shapes(scene, np.arange(scene.num_tracks))
    simulated = ~scripted & tokens[0].valid[:, kc:].any(1)
    judged = simulated & ~behind_in_lane(scene, scripted.nonzero()[0], cfg.progress_queue_m)
    edges, z = scene_road_edges(scene.road_map), scene.tracks.position[:, scene.current_frame, 2]
    on_road = _vehicles_on_road(scene, size, simulated, edges) if cfg.offroad else np.zeros(0, np.int64)
    steps = tokens[0].ids.shape[1]
    collided = offroad = 0
    last = np.full((k, scene.num_tracks), -1, np.int64)
    err = np.zeros((k, scene.num_tracks), np.float32)
    for c, mt in enumerate(tokens):
        poses, present = token_step_frames(mt, vocab, kc)
        hit = at_fault_collisions(poses, present, size)
        off = first_offroad(poses, present, size, z, edges, on_road)
        first = np.where(hit < 0, off, np.where(off < 0, hit, np.minimum(hit, off)))
        bad = (first >= 0) & simulated
        err[c] = progress_error(edited, mt, kc) * judged
        collided, offroad = collided + int(((hit >= 0) & simulated).sum()), offroad + int((off >= 0).sum())
        last[c, bad] = kc + first[bad] // FRAMES_PER_TOKEN
    ret = token_returns(last, -cfg.progress * err, steps, cfg.discount)
    adv = list(group_advantages(ret, simulated)) if rule is None else [rule[c] & simulated[:, None, None] for c in range(k)]
    progress = float(err.sum())
    last[(last < 0) | (rule is not None)] = steps  # the rule is taught on every drawn token
    n = max(simulated.sum() * k, 1)
    shares = {"penalised": float((ret[..., -1] <= -1).sum() / n), "at_fault": collided / n, "offroad": offroad / n,
              "progress_error": progress / n}
    return [edited] * k, tokens, [road] * k, adv, list(last), [scripted] * k, shares


def token_returns(penalty_step: np.ndarray, final: np.ndarray, steps: int, discount: float) -> np.ndarray:
    """[K, N, S] the return from each token step on of K rollouts of N agents: ``-discount**n`` at a step n steps
    before the agent's penalty (``penalty_step`` [K, N], -1 for none; -1 from that step on), else ``final``
    [K, N] (the episode's progress term, the same at every step)."""
    ahead = penalty_step[..., None] - np.arange(steps)  # [K, N, S] steps until the penalty
    penalised = -(discount ** np.maximum(ahead, 0)).astype(np.float32)
    return np.where((penalty_step >= 0)[..., None], penalised, final[..., None]).astype(np.float32)


def group_advantages(returns: np.ndarray, simulated: np.ndarray) -> np.ndarray:
    """[K, N, S] each return minus the same agent's mean return at that step over the K rollouts (the group
    baseline), 0 for the agents that are not ``simulated`` [N]."""
    return (returns - returns.mean(0, keepdims=True)) * simulated[:, None]


def _vehicles_on_road(scene: Scenario, size: np.ndarray, rows: np.ndarray, edges) -> np.ndarray:
    """The tracks of ``rows`` (bool) that are vehicles inside the road edges at the current frame: the
    ones the off-road penalty watches (a car parked off the road is not penalised for staying there)."""
    tr, cf = scene.tracks, scene.current_frame
    cand = np.flatnonzero(rows & (tr.types == int(AgentType.VEHICLE)) & tr.valid[:, cf])
    if edges is None or not len(cand):
        return cand[:0]
    p = tr.position[cand, cf]
    d = box_distance_to_road_edge(p[:, 0], p[:, 1], p[:, 2], size[cand, 0], size[cand, 1], size[cand, 2], tr.heading[cand, cf],
                                  edges)
    return cand[d <= 0]


# ------------------------------------------------------------------------------ the run
def train_prior_rl(cfg: PriorRLConfig) -> Path:
    """The run (module docstring); returns the path of the last checkpoint."""
    if cfg.objective not in ("rl", "rule"):
        raise ValueError(f"objective must be 'rl' or 'rule', got {cfg.objective!r}")
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ck = load_embedded() if cfg.init == "embedded" else load_checkpoint(cfg.init)
    ref = copy.deepcopy(ck.model).eval()
    for p in ref.parameters():
        p.requires_grad_(False)
    model, vocab, road_vocab = ck.model, ck.motion_vocab, ck.road_vocab
    start = 0
    last_path = out / "last"
    optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=0.0)
    if checkpoint_paths(last_path)["meta"].is_file():
        resumed = load_checkpoint(last_path)
        model.load_state_dict(resumed.model.state_dict())
        start = resumed.step
    scenes = open_scenes(cfg.scenes)
    settings = model.config.road_settings
    log = (out / "train.jsonl").open("a")
    for it in range(start, cfg.iterations):
        t0 = time.time()
        rng = np.random.default_rng([cfg.seed, it])
        generator = torch.Generator().manual_seed(cfg.seed * 100_003 + it)
        model.eval()
        parts: list[list] = [[] for _ in range(6)]
        shares = []
        for i in rng.choice(len(scenes), cfg.scenes_per_iteration, replace=False):
            scene = scenes[int(i)]
            road = scene_road(scene, road_vocab, settings)
            *group, share = rollout_group(model, scene, road, vocab, cfg, rng, generator)
            for p, g in zip(parts, group):
                p.extend(g)
            shares.append(share)
        t1 = time.time()  # the update in eval mode too (no dropout): the log-probabilities are those the draws had
        optimizer.zero_grad(set_to_none=True)
        res = update_in_parts(model, ref, parts, vocab, cfg)
        grad = torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
        optimizer.step()
        row = {"iteration": it + 1, **{key: float(np.mean([sh[key] for sh in shares])) for key in shares[0]}, **res,
               "grad_norm": float(grad),
               "rollout_s": round(t1 - t0, 2), "update_s": round(time.time() - t1, 2)}
        log.write(json.dumps(row) + "\n")
        log.flush()
        print(json.dumps(row), flush=True)
        if (it + 1) % cfg.save_every == 0 or it + 1 == cfg.iterations:
            meta = {"prior_rl": dataclasses.asdict(cfg)}
            save_checkpoint(out / f"iter{it + 1:04d}", model, vocab, road_vocab, step=it + 1, data=meta)
            save_checkpoint(last_path, model, vocab, road_vocab, step=it + 1, data=meta)
    log.close()
    return last_path


def update_in_parts(model, reference, parts: list[list], vocab: MotionVocabulary, cfg: PriorRLConfig) -> dict[str, float]:
    """The gradients of :func:`rl_loss` over all of an iteration's rollouts (``parts``: scenes, tokens, roads,
    advantages, last steps, scripted), summed one scene's rollouts at a time (``cfg.rollouts`` rows each), so that
    the activations of one scene's batch, not of the whole iteration's, are held at once. Returns the
    iteration's ``loss``, ``pg``, ``kl`` and ``tokens``."""
    sc, tok, roads, adv, last, scripted = parts
    kc, k = first_future_step(sc[0]), cfg.rollouts
    chunks = [scene_batch(sc[i:i + k], tok[i:i + k], roads[i:i + k], vocab, adv[i:i + k], last[i:i + k], scripted[i:i + k], kc)
              for i in range(0, len(sc), k)]
    total = int(sum(int(b.target_valid.sum()) for b, _ in chunks))
    out = {"loss": 0.0, "kl": 0.0, "tokens": total}
    out.update({"excluded_mass": 0.0, "ruled": 0.0} if cfg.objective == "rule" else {"pg": 0.0})
    for batch, weight in chunks:
        res = (rule_loss(model, reference, batch, weight, total=total, anchor=cfg.rule_anchor) if cfg.objective == "rule"
               else rl_loss(model, reference, batch, weight, cfg.beta, total=total))
        res["loss"].backward()
        for key in out.keys() - {"tokens"}:  # the excluded mass weighted by its rows, divided below
            out[key] += float(res[key].detach()) * (float(res["ruled"]) if key == "excluded_mass" else 1)
    if "excluded_mass" in out:
        out["excluded_mass"] /= max(out["ruled"], 1)
    return out


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    for f in dataclasses.fields(PriorRLConfig):
        kind = type(f.default)
        parser.add_argument(f"--{f.name.replace('_', '-')}", default=f.default,
                            type=(lambda v: v.lower() in ("1", "true", "yes")) if kind is bool else kind)
    cfg = PriorRLConfig(**vars(parser.parse_args(argv)))
    train_prior_rl(cfg)


if __name__ == "__main__":
    main()
