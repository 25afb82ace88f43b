"""Variants of a prior that tests step beside it (imported by the test modules, as ``fuzzing`` is)."""

from __future__ import annotations

import dataclasses

import torch

from smart_marl.model.smart import SMART

TINY_TRAIN_MODEL = {"hidden_dim": 16, "num_heads": 2, "head_dim": 8, "num_agent_blocks": 1, "num_freq_bands": 4,
                    "map_neighbours": 4, "road_neighbours": 4, "agent_neighbours": 4}
"""``model_overrides`` of a training config that make a model small enough for a test run of a few steps."""


def with_speed_change(model: SMART, last_layer_scale: float) -> SMART:
    """``model`` with ``speed_change_input`` on: its weights, the new input's last layer at ``last_layer_scale``
    times random values (0: as it starts, the same logits as ``model``)."""
    cfg = dataclasses.replace(model.config, speed_change_input=True)
    out = SMART(cfg, model.motion_contours).eval()
    missing, unexpected = out.load_state_dict(model.state_dict(), strict=False)
    assert not unexpected and missing and all(k.startswith("motion_net.speed_change.") for k in missing)
    if last_layer_scale:
        torch.manual_seed(1)
        last = out.motion_net.speed_change[-1]
        with torch.no_grad():
            last.weight.copy_(last_layer_scale * torch.randn_like(last.weight))
    return out
