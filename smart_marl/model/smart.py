"""Model stage: the SMART model (RoadNet + MotionNet + next-token heads) and its named configs.

What comes in: a :class:`~smart_marl.model.batch.SmartBatch` (padded tensors of motion tokens and
road tokens of several scenes). What goes out: per-(agent, step) features, next-motion-token
logits per agent type (each over its own vocabulary) and road next-token logits.

Named configs follow the paper's Table 6 (``smart-1m``, ``smart-7m``, ``smart-26m``,
``smart-101m``); :func:`get_config` takes a name or a dict and applies overrides.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Mapping, NamedTuple

import torch
import torch.nn as nn

from ..config_files import check_fields, flag, integer, number, one_of, sequence, text
from ..errors import SmartMarlError
from .batch import RoadSettings
from .layers import mlp
from .motionnet import NUM_MOTION_TYPES, MotionCache, MotionNet
from .roadnet import RoadNet


class ModelConfigError(SmartMarlError, ValueError):
    """An unknown model config name or field."""


@dataclass
class SmartConfig:
    """SMART hyperparameters (Table 6 of the paper, plus the dense-neighbourhood sizes)."""

    name: str = "smart-1m"
    hidden_dim: int = 64
    num_heads: int = 8
    head_dim: int = 8
    num_road_layers: int = 1
    num_agent_blocks: int = 2
    motion_vocab_sizes: tuple[int, int, int] = (512, 512, 512)  # vehicle, pedestrian, cyclist
    road_vocab_size: int = 1024
    agent_radius_m: float = 60.0
    map_radius_m: float = 30.0
    road_radius_m: float = 10.0
    temporal_window_tokens: int = 6  # 3 s
    agent_neighbours: int = 32  # K of the dense neighbourhoods
    map_neighbours: int = 32
    road_neighbours: int = 16
    road_piece_points: int = 11
    num_freq_bands: int = 64
    dropout: float = 0.1
    road_types: str = "all"  # the road kinds the type embedding tells apart (batch.ROAD_TYPE_SETS): "all" or "sumo"
    stop_signs: bool = False  # lanes a stop sign controls carry the light code FLASHING_STOP (batch.scene_road)
    speed_change_input: bool = False  # each token's speed change against the one before, an input (MotionNet.speed_change)

    def __post_init__(self) -> None:
        check_fields(self, MODEL_RULES, "model", ModelConfigError)
        self.motion_vocab_sizes = tuple(int(v) for v in self.motion_vocab_sizes)
        if self.num_heads * self.head_dim != self.hidden_dim:
            raise ModelConfigError(f"num_heads * head_dim must equal hidden_dim, got {self.num_heads} * {self.head_dim} != {self.hidden_dim}")
        size = self.approx_parameters()
        if size > MAX_MODEL_PARAMETERS:
            raise ModelConfigError(f"model config: about {size:.3g} parameters (hidden_dim {self.hidden_dim}, "
                                   f"{self.num_road_layers} road layers, {self.num_agent_blocks} agent blocks), more than the "
                                   f"limit of {MAX_MODEL_PARAMETERS:.0e} (10x smart-101m, the largest named config)")

    @property
    def road_settings(self) -> RoadSettings:
        """How this model reads a scene's road beside the pieces (``road_types``, ``stop_signs``)."""
        return RoadSettings(self.road_types, self.stop_signs)

    def approx_parameters(self) -> float:
        """About how many parameters the model has (attention layers: 12 d^2 each, three per agent block
        and one per road layer, plus the heads' last layers): within a factor 2 of the exact count."""
        d = self.hidden_dim
        layers = self.num_road_layers + 3 * self.num_agent_blocks
        return float(12 * d * d * layers + d * (sum(self.motion_vocab_sizes) + self.road_vocab_size))

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["motion_vocab_sizes"] = list(self.motion_vocab_sizes)
        return d


MAX_MODEL_PARAMETERS = 1e9
"""The largest model a config may describe (about 10x smart-101m): a checkpoint or a training config that
asks for more is refused before anything is allocated."""
MAX_VOCAB_SIZE = 8192
"""The largest motion or road vocabulary (4x smart-101m's 2048 motion tokens per type)."""
_RADIUS = number(0.0, 1000.0, low_open=True, why="metres, far beyond any scene")
MODEL_RULES = {
    "name": text, "hidden_dim": integer(1, 8192), "num_heads": integer(1, 256), "head_dim": integer(1, 8192),
    "num_road_layers": integer(1, 64), "num_agent_blocks": integer(1, 64),
    "motion_vocab_sizes": sequence(integer(1, MAX_VOCAB_SIZE, "the largest vocabulary"), length=NUM_MOTION_TYPES),
    "road_vocab_size": integer(1, MAX_VOCAB_SIZE, "the largest vocabulary"), "agent_radius_m": _RADIUS,
    "map_radius_m": _RADIUS, "road_radius_m": _RADIUS, "temporal_window_tokens": integer(1, 64, "32 s of history"),
    "agent_neighbours": integer(1, 1024), "map_neighbours": integer(1, 1024), "road_neighbours": integer(1, 1024),
    "road_piece_points": integer(2, 64), "num_freq_bands": integer(1, 1024), "dropout": number(0.0, 1.0, high_open=True),
    "road_types": one_of("all", "sumo"), "stop_signs": flag, "speed_change_input": flag,
}
"""What each SmartConfig field takes (:mod:`smart_marl.config_files` rules), checked whenever a config is made:
from a name, a training config's overrides or a checkpoint's ``model_config``."""


NAMED_CONFIGS: dict[str, dict[str, Any]] = {
    # name: (Table 6) hidden, heads x head dim, road layers, agent blocks, motion vocab per type
    "smart-1m": dict(hidden_dim=64, num_heads=8, head_dim=8, num_road_layers=1, num_agent_blocks=2, motion_vocab_sizes=(512,) * 3),
    "smart-7m": dict(hidden_dim=128, num_heads=8, head_dim=16, num_road_layers=3, num_agent_blocks=6, motion_vocab_sizes=(1024,) * 3),
    "smart-26m": dict(hidden_dim=256, num_heads=8, head_dim=32, num_road_layers=1, num_agent_blocks=6, motion_vocab_sizes=(1024,) * 3),
    "smart-101m": dict(hidden_dim=512, num_heads=8, head_dim=64, num_road_layers=3, num_agent_blocks=6, motion_vocab_sizes=(2048,) * 3),
}
PAPER_PARAMS = {"smart-1m": 1.0e6, "smart-7m": 7.2e6, "smart-26m": 26.9e6, "smart-101m": 101.0e6}


def get_config(name_or_dict: str | Mapping[str, Any], **overrides: Any) -> SmartConfig:
    """A :class:`SmartConfig` from a named config (``smart-1m`` ...) or a dict (which may itself
    name a base config under ``name``), with ``overrides`` applied."""
    if isinstance(name_or_dict, str):
        base = {"name": name_or_dict}
    else:
        base = dict(name_or_dict)
    values: dict[str, Any] = {}
    if base.get("name") is not None and base["name"] not in NAMED_CONFIGS and not isinstance(name_or_dict, Mapping):
        raise ModelConfigError(f"unknown model config {base['name']!r}; known: {', '.join(NAMED_CONFIGS)}")
    if base.get("name") in NAMED_CONFIGS:
        values.update(NAMED_CONFIGS[base["name"]])
    values.update(base)
    values.update(overrides)
    known = {f.name for f in dataclasses.fields(SmartConfig)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ModelConfigError(f"unknown model config field(s) {unknown}; known: {sorted(known)}")
    return SmartConfig(**values)


class RoadInputs(NamedTuple):
    """The road tensors :meth:`SMART.encode_road` reads, for callers that hold them loose (a
    :class:`~smart_marl.model.batch.SmartBatch` and a :class:`~smart_marl.rollout.RolloutState`
    carry the same attributes)."""

    road_points: torch.Tensor  # [B, R, P, 2] piece points in the piece's frame
    road_pose: torch.Tensor  # [B, R, 3]
    road_type: torch.Tensor  # [B, R] long
    road_light: torch.Tensor  # [B, R] long
    road_valid: torch.Tensor  # [B, R] bool


class SMART(nn.Module):
    """RoadNet + MotionNet + heads. The motion vocabularies' contours are buffers (they are part
    of the model: the token embedding reads them), shaped [V_t, 6, 4, 2] per type."""

    def __init__(self, config: SmartConfig, motion_contours: list[torch.Tensor] | None = None) -> None:
        super().__init__()
        self.config = config
        d = config.hidden_dim
        for t, v in enumerate(config.motion_vocab_sizes):
            c = torch.zeros(v, 6, 4, 2) if motion_contours is None else torch.as_tensor(motion_contours[t], dtype=torch.float32)
            if c.shape != (v, 6, 4, 2):
                raise ModelConfigError(f"motion vocabulary of type {t} has shape {tuple(c.shape)}, the config wants ({v}, 6, 4, 2)")
            self.register_buffer(f"motion_contour_{t}", c.clone())
        self.road_net = RoadNet(config)
        self.motion_net = MotionNet(config)
        self.motion_heads = nn.ModuleList(mlp(d, d, v, layers=3) for v in config.motion_vocab_sizes)
        self.road_head = mlp(d, d, config.road_vocab_size, layers=3)

    @property
    def motion_contours(self) -> list[torch.Tensor]:
        return [getattr(self, f"motion_contour_{t}") for t in range(NUM_MOTION_TYPES)]

    def encode_road(self, batch, masked: torch.Tensor | None = None, needed: torch.Tensor | None = None) -> torch.Tensor:
        """Road encodings [B, R, d] (computed once per scene at inference). ``batch``: anything with
        ``road_points``, ``road_pose``, ``road_type``, ``road_light``, ``road_valid`` (a
        :class:`~smart_marl.model.batch.SmartBatch`, a :class:`~smart_marl.rollout.RolloutState`,
        :class:`RoadInputs`). ``needed`` [B, R]: compute only the pieces read later (:meth:`RoadNet.forward`)."""
        return self.road_net(batch.road_points, batch.road_pose, batch.road_type, batch.road_light, batch.road_valid, masked,
                             needed=needed)

    def agent_features(self, tokens: torch.Tensor, agent_type: torch.Tensor, agent_shape: torch.Tensor, start_pose: torch.Tensor,
                       end_pose: torch.Tensor, valid: torch.Tensor, road_x: torch.Tensor, road_pose: torch.Tensor,
                       road_valid: torch.Tensor, nbrs=None) -> torch.Tensor:
        """MotionNet over every step: tokens [B, N, S], agent_type [B, N], agent_shape [B, N, 3],
        start_pose / end_pose [B, N, S, 3], valid [B, N, S], road encodings road_x [B, R, d] with
        road_pose [B, R, 3], road_valid [B, R] -> features [B, N, S, d]. ``nbrs``: the neighbourhoods
        of ``end_pose`` and ``valid`` when the caller has them (:meth:`MotionNet.neighbourhoods`)."""
        if nbrs is None:
            nbrs = self.motion_net.neighbourhoods(end_pose, valid, road_pose, road_valid)
        x = self.motion_net.embed_agents(tokens, agent_type, agent_shape, start_pose, end_pose, self.motion_contours, nbrs[0], valid)
        return self.motion_net(x, road_x, nbrs, tuple(tokens.shape))

    def forward(self, batch, road_masked: torch.Tensor | None = None, agent_valid: torch.Tensor | None = None,
                road_read: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """batch (SmartBatch) -> (agent features [B, N, S, d], road encodings [B, R, d]). ``agent_valid``
        [B, N, S]: the (agent, step) rows to run, when not all of ``batch.agent_valid`` (the others are
        left out of every attention and get zero features). ``road_read`` [B, R] (bool): the road pieces
        whose encodings the caller reads (e.g. the road loss's); when given, RoadNet computes only those
        and the pieces the agents attend to, and every other piece's encoding is zero."""
        valid = batch.agent_valid if agent_valid is None else agent_valid
        nbrs = self.motion_net.neighbourhoods(batch.agent_pose, valid, batch.road_pose, batch.road_valid)
        needed = None
        if road_read is not None:
            m_idx, m_mask = nbrs[2][0], nbrs[2][1]  # map neighbours: rows of the B*R road table
            needed = road_read.reshape(-1).clone()
            needed[m_idx[m_mask]] = True
            needed = needed.view_as(road_read)
        road_x = self.encode_road(batch, road_masked, needed)
        return self.agent_features(batch.agent_tokens, batch.agent_type, batch.agent_shape, batch.agent_start_pose,
                                   batch.agent_pose, valid, road_x, batch.road_pose, batch.road_valid, nbrs), road_x

    def motion_logits(self, features: torch.Tensor, agent_type: torch.Tensor) -> list[torch.Tensor]:
        """Logits of every (agent, step) under each type's head: features [..., d] -> per type
        [..., V_t] (pick the row's own type with ``agent_type``). For training use :mod:`.losses`,
        which runs each head only on its type's rows; for sampling :meth:`next_token_logits`."""
        return [head(features) for head in self.motion_heads]

    # ------------------------------------------------------------------------------ inference
    def start_cache(self, road_x: torch.Tensor, road_pose: torch.Tensor, road_valid: torch.Tensor, scene_of_group: torch.Tensor,
                    agent_type: torch.Tensor, agent_shape: torch.Tensor) -> MotionCache:
        """An empty KV cache for incremental decoding (:meth:`MotionNet.start_cache`)."""
        return self.motion_net.start_cache(road_x, road_pose, road_valid, scene_of_group, agent_type, agent_shape,
                                           self.motion_contours)

    def step(self, cache: MotionCache, tokens: torch.Tensor, start_pose: torch.Tensor, end_pose: torch.Tensor,
             valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One token step of every agent against the KV cache -> (rows [Q], features [Q, d])
        (:meth:`MotionNet.step`); :meth:`next_token_logits` turns the features into logits."""
        return self.motion_net.step(cache, tokens, start_pose, end_pose, valid)

    @torch.no_grad()
    def next_token_logits(self, features: torch.Tensor, agent_type: torch.Tensor) -> torch.Tensor:
        """Each row's next-token logits under its own type's head: features [Q, d], agent_type [Q]
        (0..2) -> [Q, Vmax] float32, ``-inf`` beyond the row's type's vocabulary size."""
        sizes = [int(v) for v in self.config.motion_vocab_sizes]
        out = torch.full((agent_type.shape[0], max(sizes)), float("-inf"), device=agent_type.device)
        for t, head in enumerate(self.motion_heads):
            sel = agent_type == t
            logits = head(features[sel])  # (Q_t, V_t)
            if logits.shape[0]:
                out[sel, : sizes[t]] = logits.float()  # float32 from here on, whatever the model's precision
        return out


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def model_parameter_count(config: SmartConfig) -> int:
    """Parameter count of a config without allocating its weights (meta device)."""
    with torch.device("meta"):
        return count_parameters(SMART(config))
