"""Subcommands of the smart-marl command line (see smart_marl.cli)."""
