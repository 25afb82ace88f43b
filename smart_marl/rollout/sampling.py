"""Rollout stage, sampler: next-token logits -> chosen motion tokens (SMART's top-k sampling).

What comes in: padded per-agent logits ``[..., Vmax]`` whose entries beyond an agent type's
vocabulary are ``-inf`` (see :meth:`smart_marl.model.SMART.next_token_logits`), a temperature, ``k``, a ``torch.Generator``
and optional forced tokens. What goes out: token ids and their log-probabilities under the
temperature-scaled, *unclipped* distribution (``log_softmax(logits / temperature)``), which is
what a policy's KL to the prior and the likelihood of a rollout are measured with.

Sampling draws from the ``k`` most likely tokens with their probabilities renormalised (the
paper's top-k, k = 5); ``k <= 0`` or ``k >= V`` means the whole distribution. With a seeded
generator on the CPU the draws are reproducible.

:func:`reference_log_probs` is the distribution :func:`sample_tokens` draws from, as
log-probabilities over the whole vocabulary (``-inf`` outside the top ``k``), and
:func:`top_k_mask` its support: the one definition of "the prior as it drives" that the
environment's action mask, a fine-tuned policy's mask and the KL to the prior all use.

"No prior" is a row of logits that are all zero (:func:`no_prior_logits`; a real row has ``-inf``
beyond the type's tokens and is never all zero): the environment gives it for an agent the prior does
not drive (done, not simulated, no finite logit), and :func:`has_prior_logits` is the one test of it
(the KL to the prior and the action mask leave such rows out).
"""

from __future__ import annotations

import numpy as np
import torch

from ..config_files import number

TEMPERATURE_RANGE = (1e-3, 1e3)
"""The temperatures the prior samples with, everywhere a user gives one (env, fine-tuning, eval, what-if):
below 1e-3 ``logits / T`` overflows float32 into NaN probabilities; above 1e3 every token is as likely."""
temperature_rule = number(*TEMPERATURE_RANGE, why="beyond it every token is as likely")
"""The rule (:mod:`smart_marl.config_files`) of a temperature: a finite number in :data:`TEMPERATURE_RANGE`."""

DEFAULT_TOP_K = 6
"""The k the prior drives with unless told otherwise (rollouts, the environment's background, what-if
scenarios, ``smart-marl eval``). The paper samples among 5. Measured on the embedded prior (docs/experiments/,
the stage log), on the held-out real scenes at two seeds: k = 6 is as realistic as k = 8 (meta-metric
0.704 / 0.702 against 0.705 / 0.699) and keeps vehicles' speed better late in a rollout (rollout / log
speed at 8 s 0.89-0.90 against 0.85-0.87 over three seeds); smaller k costs kinematic realism, larger k
costs speed and, beyond 8, interactive realism."""


def any_rows(mask: torch.Tensor) -> torch.Tensor:
    """``mask.any(-1)`` of a bool tensor, read as bytes (the same result; on the CPU a bool reduction over
    a [1200, 1024] mask takes 0.4 ms, the bytes' maximum 0.02)."""
    return mask.contiguous().view(torch.uint8).amax(-1).bool() if mask.shape[-1] else mask.any(-1)


def sample_tokens(logits: torch.Tensor, generator: torch.Generator, top_k: int = DEFAULT_TOP_K, temperature: float = 1.0,
                  forced: torch.Tensor | None = None, exclude: torch.Tensor | None = None,
                  top: tuple[torch.Tensor, torch.Tensor] | None = None,
                  log_probs_of: str = "all", scored: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Top-k sampling with renormalised probabilities.

    logits [..., V] (``-inf`` for tokens outside the agent's vocabulary; a row must have at
    least one finite entry), forced [...] int64 (``-1``: sample; otherwise that token is taken),
    exclude [..., V] bool (tokens that may not be drawn: the top k are taken among the others; a row
    must keep at least one finite entry) -> (tokens [...] int64, log_probs [...] under
    ``log_softmax(logits / temperature)``, the distribution before ``exclude``). ``top``:
    ``torch.topk(logits, top_k + 1)`` [M, k + 1] where the caller has it (read, at temperature 1, instead
    of ranking again; rows with equal values among them are ranked again, so the draw is the same).
    ``log_probs_of``: ``"all"`` rows, or ``"forced"`` rows only (the others' log-probability is 0; the
    ``log_softmax`` over [M, V] is the sampler's largest cost after ranking). ``scored``: the logits [..., V] the
    log-probabilities are of, when the draw ranks and samples from other ones (default: ``logits``; speed persistence,
    :mod:`~smart_marl.rollout.persistence`, tilts what is sampled and reports the model's log-probabilities).
    """
    if temperature <= 0:
        raise ValueError(f"temperature must be > 0, got {temperature}")
    if log_probs_of not in ("all", "forced"):  # before the draw: a refused call leaves the generator as it was
        raise ValueError(f"log_probs_of must be 'all' or 'forced', got {log_probs_of!r}")
    lead, v = logits.shape[:-1], logits.shape[-1]
    flat = logits.reshape(-1, v)  # (M, V)
    if temperature != 1.0:  # dividing by 1 changes nothing (and is a pass over [M, V])
        flat = flat / temperature
    k = v if top_k is None or top_k <= 0 else min(int(top_k), v)
    if top is not None and temperature == 1.0 and k < v:
        top_val, top_idx = _first_k(flat, top, k)
    else:
        top_val, top_idx = torch.topk(flat, k, dim=-1)  # (M, k), -inf entries (beyond the type's size) get zero probability
    if exclude is not None:  # the top k of the rows that lose a token (topk is row by row: the others' stay as they are)
        ex = exclude.reshape(-1, v)
        r = any_rows(ex).nonzero().squeeze(1)
        if len(r):
            top_val[r], top_idx[r] = torch.topk(flat[r].masked_fill_(ex[r], float("-inf")), k, dim=-1)
    probs = torch.softmax(top_val, dim=-1)
    if flat.shape[0]:
        pick = torch.multinomial(probs, 1, generator=generator)  # (M, 1)
        tokens = top_idx.gather(1, pick).squeeze(1)
    else:
        tokens = torch.zeros(0, dtype=torch.long, device=logits.device)
    if forced is not None:
        f = forced.reshape(-1).to(tokens.device)
        tokens = torch.where(f >= 0, f, tokens)
    if scored is not None and scored is not logits:
        flat = scored.reshape(-1, v) if temperature == 1.0 else scored.reshape(-1, v) / temperature
    if log_probs_of == "all":
        log_probs = torch.log_softmax(flat, dim=-1).gather(1, tokens[:, None]).squeeze(1)
    else:  # the forced rows', row by row: the same values as over every row
        at = (f >= 0).nonzero().squeeze(1) if forced is not None else tokens[:0]
        log_probs = torch.zeros(tokens.shape, dtype=flat.dtype, device=flat.device)
        log_probs[at] = torch.log_softmax(flat.index_select(0, at), dim=-1).gather(1, tokens[at, None]).squeeze(1)
    return tokens.view(lead), log_probs.view(lead)


def _first_k(flat: torch.Tensor, top: tuple[torch.Tensor, torch.Tensor], k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``torch.topk(flat, k)`` read off ``top`` = ``torch.topk(flat, k + 1)``: where the k + 1 values are
    distinct, the first k are the same values and indices in the same order; rows with equal values
    (which ``topk`` may order either way) are ranked again."""
    vals, idx = top
    top_val, top_idx = vals[:, :k].clone(), idx[:, :k].clone()
    tie = (vals[:, 1:] == vals[:, :-1]).any(-1).nonzero().squeeze(1)
    if len(tie):
        top_val[tie], top_idx[tie] = torch.topk(flat[tie], k, dim=-1)
    return top_val, top_idx


def top_k_mask(logits: torch.Tensor, top_k: int | None) -> torch.Tensor:
    """bool [..., V]: the ``top_k`` largest entries of each row of ``logits`` [..., V] (the tokens
    :func:`sample_tokens` can draw; ``torch.topk``, so ties break as it breaks them). ``top_k``
    None, <= 0 or >= V: every token."""
    v = logits.shape[-1]
    if top_k is None or top_k <= 0 or top_k >= v:
        return torch.ones(logits.shape, dtype=torch.bool, device=logits.device)
    idx = torch.topk(logits, int(top_k), dim=-1).indices
    return torch.zeros(logits.shape, dtype=torch.bool, device=logits.device).scatter(-1, idx, True)


def reference_log_probs(logits: torch.Tensor, top_k: int | None = None, temperature: float = 1.0) -> torch.Tensor:
    """log-probabilities [..., V] of the distribution :func:`sample_tokens` samples with these
    arguments: ``softmax(logits / temperature)`` restricted to the ``top_k`` tokens and
    renormalised, ``-inf`` outside them (``top_k`` None: the full softmax)."""
    if temperature <= 0:
        raise ValueError(f"temperature must be > 0, got {temperature}")
    scaled = logits / temperature
    keep = top_k_mask(scaled, top_k)
    return torch.log_softmax(scaled.masked_fill(~keep, float("-inf")), dim=-1)



def reference_name(top_k: int | None, temperature: float = 1.0) -> str:
    """How a reference distribution (or a prior policy) is named in tables, logs and the env:
    ``"prior top-5"``, ``"prior full softmax"``, with ``" T=0.8"`` when the temperature is not 1."""
    name = f"prior top-{int(top_k)}" if top_k else "prior full softmax"
    return name if float(temperature) == 1.0 else f"{name} T={float(temperature):g}"


def no_prior_logits(size: int) -> np.ndarray:
    """The "no prior" row: ``size`` zero logits (float32), for an agent the prior does not drive."""
    return np.zeros(size, np.float32)


def has_prior_logits(logits):
    """Which rows of ``logits`` [..., V] (numpy or torch) are the prior's, not the "no prior" row of
    :func:`no_prior_logits`: bool [...]."""
    return (logits != 0).any(-1)
