"""The ``smart-marl`` command line: one subcommand per job, each defined next to the code it runs.

Every subcommand module exposes ``register(subparsers)``, which adds its parser and sets
``func`` (called with the parsed args, returning an exit code). Exit codes: 0 success, 1 the job
failed on bad input (the message names the file and record), 2 bad arguments (argparse's checks
and the :class:`~smart_marl.errors.UsageError` of a value check, one ``error:`` line).

The commands of :mod:`smart_marl.commands` are listed below; commands of other packages (``agents``'
``finetune`` and ``whatif``) are found through the ``smart_marl.commands`` entry-point group
(``[project.entry-points."smart_marl.commands"]`` in their pyproject.toml, ``NAME =
"module:register"``), so smart_marl never imports them.
"""

from __future__ import annotations

import argparse
import sys
from importlib.metadata import entry_points

from .commands import demo, generate_sumo, info, models, preprocess, pretokenize, train, vocab
from .commands import eval as eval_command
from .errors import SmartMarlError, UsageError

# Modules that add subcommands, in the order --help lists them (entry-point commands follow, by name).
_COMMAND_MODULES = (info, preprocess, pretokenize, demo, train, models, generate_sumo, vocab, eval_command)
COMMAND_GROUP = "smart_marl.commands"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="smart-marl",
        description="SMART behaviour prior for multi-agent driving: read scenes, build caches, tokenize, train, simulate.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module in _COMMAND_MODULES:
        module.register(sub)
    for ep in sorted(entry_points(group=COMMAND_GROUP), key=lambda e: e.name):
        ep.load()(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra and isinstance(getattr(args, "overrides", None), list) and all("=" in e and not e.startswith("-") for e in extra):
        args.overrides = [*args.overrides, *extra]  # key=value overrides after an option (`train --seed 1 lr=1e-3`)
    elif extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    try:
        return int(args.func(args) or 0)
    except UsageError as exc:  # a bad argument or config value found after parsing
        print(f"smart-marl {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except SmartMarlError as exc:
        print(f"smart-marl {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"smart-marl {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
