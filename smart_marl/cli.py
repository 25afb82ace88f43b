"""The ``smart-marl`` command line: one subcommand per job, each defined next to the code it runs.

Every subcommand module exposes ``register(subparsers)``, which adds its parser and sets
``func`` (called with the parsed args, returning an exit code). Exit codes: 0 success, 1 the job
failed on bad input (the message names the file and record), 2 bad arguments (argparse's checks
and the :class:`~smart_marl.errors.UsageError` of a value check, one ``error:`` line).
"""

from __future__ import annotations

import argparse
import importlib
import sys

from .errors import SmartMarlError, UsageError

# Modules that add subcommands, in the order --help lists them.
_COMMAND_MODULES = (
    "smart_marl.commands.info",
    "smart_marl.commands.preprocess",
    "smart_marl.commands.demo",
    "smart_marl.commands.train",
    "smart_marl.commands.models",
    "smart_marl.commands.generate_sumo",
    "smart_marl.commands.vocab",
    "smart_marl.commands.eval",
    "smart_marl.commands.finetune",
    "smart_marl.commands.whatif",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="smart-marl",
        description="SMART behaviour prior for multi-agent driving: read scenes, build caches, tokenize, train, simulate.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in _COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
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
