"""Fine-tuning stage, the networks and the policies that act on the batched environment's tensors.

What comes in: observations [..., A, D] and the prior's logits [..., A, V] of the agents of a group
(the batched env's ``("agents", "observation", ...)``). What goes out: the actor's logits
(:class:`PolicyLogits`), the critic's values (:class:`Critic`), their checkpoints
(:func:`save_policy` / :func:`load_policy`: safetensors + JSON, no pickle) and, for evaluation and
benchmarks, policies that pick every agent's token of every scene at once (:class:`TensorPolicy`:
the prior at a top-k or its full softmax, a fine-tuned actor, the log-following expert).

The actor: logits ``prior_logits / T + f(obs)`` (``residual``, ``f`` a shared-parameter
``MultiAgentMLP`` whose last layer starts at 0, so training starts exactly at the reference) or
``f(obs)`` alone, restricted to the reference's support (the prior's top ``reference_top_k``
tokens). ``actor_head="per_token"``: ``f`` has one output per token id; ``"motion"``: ``f`` weighs a
few features of each token's motion (:func:`token_motion_features`), so what is learnt about one
token carries over to tokens that move alike.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file
from torch import nn
from torchrl.modules import MultiAgentMLP

from envs._observation import ObservationConfig, observation_layout
from envs.smart_traffic_batched_v0 import MAX_AGENT_SLOTS
from smart_marl.config_files import check_value, integer, optional, shown
from smart_marl.errors import SmartMarlError, check_regular_file
from smart_marl.model.smart import MAX_VOCAB_SIZE
from smart_marl.rollout import reference_log_probs, reference_name, sample_tokens, top_k_mask
from smart_marl.scenario import AgentType

from .scripted import log_following_tokens

ACTOR_HEADS = ("per_token", "motion")
MOTION_FEATURE_SIZE = 6
"""P, the features per token of :func:`token_motion_features` (the ``"motion"`` head's last layer width)."""
MAX_OBS_DIM = 65_536
"""The widest observation a policy checkpoint may declare (the default layout's is 473 numbers; every
observation option at its limit stays far below)."""
EMBEDDED_POLICY_DIR = Path(__file__).resolve().parent / "checkpoints"
"""Where the package's fine-tuned policy lives (``load_policy("embedded")``; its card: docs/policy_card.md)."""


def prior_digest(model) -> str:
    """sha256 of a SMART model's weights (its state dict in name order): what a policy was trained
    against, so that loading it next to another prior is refused (its logits are the prior's plus a
    learned residual, meaningless on top of other logits)."""
    import hashlib

    h = hashlib.sha256()
    for name, t in sorted(model.state_dict().items()):
        h.update(name.encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def resolve_policy_path(path: str | Path) -> Path:
    """``"embedded"``: the package's fine-tuned policy; anything else is a checkpoint path."""
    if isinstance(path, str) and path == "embedded":
        found = sorted(EMBEDDED_POLICY_DIR.glob("*.json")) if EMBEDDED_POLICY_DIR.is_dir() else []
        if not found:
            raise PolicyError(f"{EMBEDDED_POLICY_DIR}: this installation ships no fine-tuned policy; pass a checkpoint path")
        return found[0]
    return Path(path)


class PolicyError(SmartMarlError, ValueError):
    """A policy checkpoint or network that cannot be used."""


def token_end_poses(vocab, vocab_size: int) -> tuple[torch.Tensor, list[int]]:
    """([3, V, 3] where every token of each type's vocabulary (vehicle, pedestrian, cyclist) ends after
    0.5 s in its start frame: forward m, left m, turn rad; the types in the group). A type whose
    vocabulary has another size than ``vocab_size`` (the group's action space) gets zeros and is left
    out of the list: its agents are not in the group."""
    out, types = torch.zeros(3, vocab_size, 3), []
    for t in range(3):
        tv = vocab[AgentType(t)]
        if tv.size == vocab_size:
            out[t] = torch.as_tensor(tv.poses[:, -1], dtype=torch.float32)
            types.append(t)
    return out, types


def token_motion_features(vocab, vocab_size: int) -> torch.Tensor:
    """[3, V, 6] features of every token of each type's vocabulary: where it ends
    (:func:`token_end_poses`) and the squares (a weight on both can favour a band: -a (x - c)^2), each
    standardised over the type's tokens; zeros for a type not in the group."""
    ends, types = token_end_poses(vocab, vocab_size)
    out = torch.zeros(3, vocab_size, MOTION_FEATURE_SIZE)
    for t in types:
        feat = torch.cat([ends[t], ends[t].square()], -1)
        out[t] = (feat - feat.mean(0)) / feat.std(0).clamp(min=1e-6)
    return out


class PolicyLogits(nn.Module):
    """Logits over the motion vocabulary for every agent of the group (module docstring).
    observation [..., A, O], prior_logits [..., A, V] -> [..., A, V], ``-inf`` outside the prior's
    ``top_k`` tokens (:func:`smart_marl.rollout.top_k_mask`; None: every token).

    ``motion_features`` None: ``f(obs)`` has one output per token. Else ([3, V, P],
    :func:`token_motion_features`): ``f(obs)`` gives P weights and a token's output is their dot
    product with its type's features (the type read from the observation's ``ego_type`` one-hot;
    a padded agent's zeros give 0)."""

    def __init__(self, obs_dim: int, vocab_size: int, n_agents: int, hidden: int, depth: int, residual: bool = True,
                 obs_scale: float = 0.1, temperature: float = 1.0, top_k: int | None = None,
                 motion_features: torch.Tensor | None = None) -> None:
        super().__init__()
        self.residual, self.obs_scale, self.temperature = bool(residual), float(obs_scale), float(temperature)
        self.top_k = None if top_k is None else int(top_k)
        if motion_features is not None:
            if tuple(motion_features.shape[:2]) != (3, vocab_size):
                raise PolicyError(f"motion_features must be [3, {vocab_size}, P], got {list(motion_features.shape)}")
            self.register_buffer("motion_features", motion_features.float())
            layout = {name: (off, size) for name, off, size in observation_layout(ObservationConfig())}
            off, size = layout["ego_type"]
            self.type_slice = slice(off, off + size)
        else:
            self.motion_features = None
        out_dim = vocab_size if motion_features is None else int(motion_features.shape[-1])
        self.f = MultiAgentMLP(obs_dim, out_dim, n_agents, centralized=False, share_params=True, depth=depth,
                               num_cells=hidden, activation_class=nn.Tanh)
        if self.residual:  # start exactly at the prior
            last = max(int(name.split(".")[1]) for name, _ in self.f.named_parameters())
            with torch.no_grad():
                for name, p in self.f.named_parameters():
                    if int(name.split(".")[1]) == last:
                        p.zero_()

    def forward(self, observation: torch.Tensor, prior_logits: torch.Tensor) -> torch.Tensor:
        delta = self.f(observation * self.obs_scale)
        if self.motion_features is not None:  # P weights per agent -> one output per token of its type
            delta = torch.einsum("...ap,...at,tvp->...av", delta, observation[..., self.type_slice], self.motion_features)
        logits = prior_logits / self.temperature + delta if self.residual else delta
        if self.top_k is None:
            return logits
        return logits.masked_fill(~top_k_mask(prior_logits, self.top_k), float("-inf"))


class Critic(nn.Module):
    """State value per agent [..., A, 1]: centralised (MAPPO) or per agent (IPPO)."""

    def __init__(self, obs_dim: int, n_agents: int, hidden: int, depth: int, centralized: bool, obs_scale: float = 0.1) -> None:
        super().__init__()
        self.obs_scale = float(obs_scale)
        self.v = MultiAgentMLP(obs_dim, 1, n_agents, centralized=centralized, share_params=True, depth=depth, num_cells=hidden,
                               activation_class=nn.Tanh)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.v(observation * self.obs_scale)


# ------------------------------------------------------------------------------ checkpoints
def save_policy(path: Path, config: dict, net: PolicyLogits, critic: nn.Module, dims: dict, iteration: int, metrics: dict) -> Path:
    """``path.safetensors`` (actor and critic weights) + ``path.json`` (the run's config, the network's
    sizes, the iteration, metrics), each written to a temporary name and renamed."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tensors = {f"actor.{k}": v.detach().cpu().contiguous() for k, v in net.state_dict().items()}
    tensors.update({f"critic.{k}": v.detach().cpu().contiguous() for k, v in critic.state_dict().items()})
    tmp = path.with_name(path.name + ".safetensors.tmp")
    save_file(tensors, str(tmp))
    tmp.replace(path.with_name(path.name + ".safetensors"))
    meta = {"format": "smart-marl-policy", "version": 1, "config": config, **dims, "iteration": iteration, "metrics": metrics}
    jtmp = path.with_name(path.name + ".json.tmp")
    jtmp.write_text(json.dumps(meta, indent=1, default=float))
    jtmp.replace(path.with_name(path.name + ".json"))
    return path.with_name(path.name + ".json")


def policy_files(path: str | Path) -> tuple[Path, Path]:
    """(``NAME.json``, ``NAME.safetensors``) of a policy checkpoint given as ``NAME``, either file, or
    ``"embedded"`` (the package's)."""
    p = resolve_policy_path(path)
    stem = p.with_suffix("") if p.suffix in (".json", ".safetensors") else p
    return stem.with_name(stem.name + ".json"), stem.with_name(stem.name + ".safetensors")


def _sha256_rule(value) -> str | None:
    ok = isinstance(value, str) and len(value) == 64 and all(c in "0123456789abcdef" for c in value)
    return None if ok else f"must be a sha256 digest (64 lowercase hex digits), got {shown(value)}"


_POLICY_META_RULES = {
    "obs_dim": integer(1, MAX_OBS_DIM, "wider than any observation layout"),
    "vocab_size": integer(1, MAX_VOCAB_SIZE, "the largest vocabulary"),
    "n_agents": integer(1, MAX_AGENT_SLOTS, "the batched env's most agent slots"),
    "prior_sha256": optional(_sha256_rule),
    "config": lambda v: None if isinstance(v, dict) and all(isinstance(k, str) for k in v)
    else f"must be a mapping of fine-tuning config fields, got {shown(v)}",
}
"""What the JSON half of a policy checkpoint holds besides ``format`` (its ``config`` is checked by the
fine-tuning config's rules when it is loaded, :func:`agents.finetune.load_policy`)."""


def read_policy(path: str | Path) -> tuple[dict, dict[str, torch.Tensor]]:
    """(meta, weights) of a policy checkpoint (``NAME``, ``NAME.json`` or ``NAME.safetensors``, or
    ``"embedded"``: the package's). Checked before anything uses it: the meta's sizes bounded
    (:data:`_POLICY_META_RULES`), every tensor floating point and finite; a problem is a
    :class:`PolicyError` naming the file and the field or tensor. Which tensors with which shapes the
    network of its config needs is :func:`check_policy_tensors`."""
    jpath, wpath = policy_files(path)
    if not jpath.is_file() or not wpath.is_file():
        raise PolicyError(f"{path}: not a policy checkpoint (needs {jpath.name} and {wpath.name})")
    for f in (jpath, wpath):  # FIFOs, devices and /proc files are refused before they are read
        check_regular_file(f, lambda name, problem: PolicyError(f"{name}: {problem}"))
    try:
        meta = json.loads(jpath.read_text())
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise PolicyError(f"{jpath}: not a readable policy checkpoint ({exc})") from exc
    if not isinstance(meta, dict) or meta.get("format") != "smart-marl-policy":
        raise PolicyError(f"{jpath}: not a smart-marl policy checkpoint (format {meta.get('format') if isinstance(meta, dict) else None!r})")
    meta.setdefault("config", {})
    for key, rule in _POLICY_META_RULES.items():
        check_value(key, meta.get(key), rule, PolicyError, str(jpath))
    try:
        weights = load_file(str(wpath))
    except Exception as exc:  # noqa: BLE001 - safetensors raises several kinds for a damaged file
        raise PolicyError(f"{wpath}: not a readable safetensors file ({exc})") from exc
    for name, t in sorted(weights.items()):
        if not t.is_floating_point():
            raise PolicyError(f"{wpath}: tensor {name} is {str(t.dtype).removeprefix('torch.')}; a policy's tensors are floating point")
        if not bool(torch.isfinite(t).all()):
            raise PolicyError(f"{wpath}: tensor {name} holds NaN or infinite values")
    return meta, weights


def policy_tensor_shapes(meta: dict, hidden: int, depth: int, residual: bool, actor_head: str, critic: str) -> dict[str, tuple[int, ...]]:
    """{tensor name: shape} of every tensor a policy checkpoint of this network holds (``actor.*`` and
    ``critic.*``, as :func:`save_policy` writes them): the networks built on the meta device (no memory,
    no weights) from the checkpoint's sizes (``meta``: obs_dim, vocab_size, n_agents, already bounded by
    :func:`read_policy`) and its config's fields."""
    with torch.device("meta"):
        features = torch.zeros(3, meta["vocab_size"], MOTION_FEATURE_SIZE) if actor_head == "motion" else None
        net = PolicyLogits(meta["obs_dim"], meta["vocab_size"], meta["n_agents"], hidden, depth, residual, motion_features=features)
        value = Critic(meta["obs_dim"], meta["n_agents"], hidden, depth, centralized=critic == "mappo")
    shapes = {f"actor.{k}": tuple(v.shape) for k, v in net.state_dict().items()}
    shapes.update({f"critic.{k}": tuple(v.shape) for k, v in value.state_dict().items()})
    return shapes


def check_policy_tensors(weights: dict[str, torch.Tensor], shapes: dict[str, tuple[int, ...]], path, network: str = "") -> None:
    """A :class:`PolicyError` naming ``path`` and the tensor unless ``weights`` holds exactly the tensors
    of ``shapes`` (:func:`policy_tensor_shapes`), each with its shape: none missing (a layer would keep
    its random start), none extra, none of another shape. ``network``: the config fields it was built
    with, for the message."""
    its = f"the network of its config{f' ({network})' if network else ''}"
    missing, extra = sorted(set(shapes) - set(weights)), sorted(set(weights) - set(shapes))
    if missing:
        raise PolicyError(f"{path}: tensor {missing[0]} is missing ({len(missing)} of the {len(shapes)} tensors of {its})")
    if extra:
        raise PolicyError(f"{path}: tensor {extra[0]} is not a tensor of {its} ({len(extra)} extra)")
    for name, want in shapes.items():
        if tuple(weights[name].shape) != want:
            raise PolicyError(f"{path}: tensor {name} has shape {list(weights[name].shape)}, {its} needs {list(want)}")


def actor_from_weights(meta: dict, weights: dict, hidden: int, depth: int, residual: bool, obs_scale: float, temperature: float,
                       top_k: int | None, actor_head: str, path="policy") -> PolicyLogits:
    """The actor network of a checkpoint with its weights."""
    features = weights.get("actor.motion_features")  # saved with the weights (a buffer): no vocabulary needed here
    if (features is not None) != (actor_head == "motion"):
        raise PolicyError(f"{path}: actor_head {actor_head!r} does not match the saved weights")
    net = PolicyLogits(meta["obs_dim"], meta["vocab_size"], meta["n_agents"], hidden, depth, residual, obs_scale, temperature, top_k,
                       None if features is None else torch.zeros_like(features))
    try:
        net.load_state_dict({k[len("actor."):]: v for k, v in weights.items() if k.startswith("actor.")})
    except RuntimeError as exc:
        raise PolicyError(f"{path}: the weights do not fit the network of its config ({str(exc)[:300]})") from exc
    return net.eval()


# ------------------------------------------------------------------------- tensor policies
class TensorPolicy:
    """A policy for every controlled agent of every scene of a :class:`envs._core.TrafficCore` at
    once: ``log_probs(core, observation [B, A, D], prior_logits [B, A, V]) -> [B, A, V]`` is its
    distribution and ``act`` samples it (top ``top_k``, from a generator seeded by :meth:`reset`), so
    two policies with equal distributions take equal actions on equal seeds."""

    name = "policy"
    top_k: int | None = None

    def reset(self, seed: int) -> None:
        self.generator = torch.Generator().manual_seed(int(seed))

    def log_probs(self, core, observation: torch.Tensor, prior_logits: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def act(self, log_probs: torch.Tensor) -> torch.Tensor:
        b, a, v = log_probs.shape
        tokens, _ = sample_tokens(log_probs.reshape(b * a, v).cpu(), self.generator, top_k=self.top_k)
        return tokens.view(b, a).to(log_probs.device)


class PriorTensorPolicy(TensorPolicy):
    """The prior as it drives: its ``softmax(logits / T)`` on its top ``top_k`` tokens (None: all)."""

    def __init__(self, top_k: int | None = None, temperature: float = 1.0) -> None:
        self.top_k, self.temperature = top_k, float(temperature)
        self.name = reference_name(top_k, temperature)

    def log_probs(self, core, observation, prior_logits):
        return reference_log_probs(prior_logits, self.top_k, self.temperature)


class FinetunedTensorPolicy(TensorPolicy):
    """A fine-tuned actor, sampled with its reference's top-k (at its start it draws what the prior
    top-k draws)."""

    name = "fine-tuned"

    def __init__(self, net: PolicyLogits) -> None:
        self.net = net.eval()
        self.top_k = net.top_k

    @torch.no_grad()
    def log_probs(self, core, observation, prior_logits):
        dev = next(self.net.parameters()).device
        a = self.net.f.n_agents
        if observation.shape[-2] != a:
            raise PolicyError(f"the policy was trained for {a} agents per scene, the env has {observation.shape[-2]}")
        return torch.log_softmax(self.net(observation.to(dev), prior_logits.to(dev)), -1).to(observation.device)


class ExpertTensorPolicy(TensorPolicy):
    """The log-following expert (:func:`agents.scripted.log_following_tokens`): one-hot on its token."""

    name = "expert (log)"
    top_k = 1

    def log_probs(self, core, observation, prior_logits):
        return _one_hot_log_probs(log_following_tokens(core), prior_logits)


def _one_hot_log_probs(tokens: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """[..., V] log-probabilities of a deterministic choice: 0 on ``tokens`` [...], -inf elsewhere (shaped as ``like``)."""
    out = torch.full(like.shape, float("-inf"), device=like.device)
    return out.scatter(-1, tokens[..., None].to(out.device), 0.0)


def expert_within_top_k(core, prior_logits: torch.Tensor, k: int | None) -> torch.Tensor:
    """[B, C] the log-following expert restricted to the prior's top ``k`` tokens (those of
    :func:`~smart_marl.rollout.top_k_mask`, the action space of a policy with ``reference_top_k=k``): of
    them, the token that, followed by any token, comes closest to the logged path over the next two
    token steps (:func:`agents.scripted.log_following_tokens` with ``allowed``). Padded and done slots: 0."""
    return log_following_tokens(core, allowed=top_k_mask(prior_logits, k)).to(prior_logits.device)


class ExpertWithinTopK(TensorPolicy):
    """The log-following expert restricted to the prior's top ``k`` tokens (:func:`expert_within_top_k`):
    how good a policy acting in that space can be. One-hot on its token."""

    top_k = 1

    def __init__(self, k: int) -> None:
        self.k, self.name = int(k), f"expert within prior top-{k}"

    def log_probs(self, core, observation, prior_logits):
        return _one_hot_log_probs(expert_within_top_k(core, prior_logits, self.k), prior_logits)


__all__ = ["ACTOR_HEADS", "Critic", "ExpertTensorPolicy", "ExpertWithinTopK", "FinetunedTensorPolicy", "PolicyError",
           "MAX_OBS_DIM", "MOTION_FEATURE_SIZE", "PolicyLogits", "PriorTensorPolicy", "TensorPolicy", "actor_from_weights",
           "check_policy_tensors", "expert_within_top_k", "policy_files", "policy_tensor_shapes", "read_policy", "save_policy",
           "token_end_poses", "token_motion_features"]
