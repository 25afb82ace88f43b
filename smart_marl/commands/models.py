"""``smart-marl models``: the named SMART configs with their parameter counts (paper Table 6)."""

from __future__ import annotations

import json

from ..model.smart import NAMED_CONFIGS, PAPER_PARAMS, get_config, model_parameter_count


def register(subparsers) -> None:
    p = subparsers.add_parser("models", help="list the named SMART configs and their parameter counts",
                              description="One line per named config: hidden size, heads x head dim, road layers, agent "
                                          "blocks, motion vocabulary per type, road vocabulary, parameters (and the paper's).")
    p.add_argument("--json", action="store_true", help="one JSON object per line")
    p.set_defaults(func=run)


def run(args) -> int:
    for name in NAMED_CONFIGS:
        cfg = get_config(name)
        n = model_parameter_count(cfg)
        row = {"name": name, "parameters": n, "paper_parameters": int(PAPER_PARAMS[name]), "hidden_dim": cfg.hidden_dim,
               "num_heads": cfg.num_heads, "head_dim": cfg.head_dim, "road_layers": cfg.num_road_layers,
               "agent_blocks": cfg.num_agent_blocks, "motion_vocab": cfg.motion_vocab_sizes[0], "road_vocab": cfg.road_vocab_size}
        if args.json:
            print(json.dumps(row))
        else:
            print(f"{name:<11} params={n / 1e6:7.2f}M (paper {PAPER_PARAMS[name] / 1e6:.1f}M)  hidden={cfg.hidden_dim:<4} "
                  f"heads={cfg.num_heads}x{cfg.head_dim:<3} road_layers={cfg.num_road_layers} agent_blocks={cfg.num_agent_blocks} "
                  f"motion_vocab={cfg.motion_vocab_sizes[0]}/type road_vocab={cfg.road_vocab_size}")
    return 0
