"""The ``smart-marl`` subcommands that live in ``agents`` (``finetune``, ``whatif``).

smart_marl never imports agents (imports go smart_marl <- envs <- agents), so the command line
finds these through the ``smart_marl.commands`` entry-point group (``[project.entry-points]`` in
pyproject.toml): each entry point names a ``register(subparsers)`` function, as the command
modules of :mod:`smart_marl.commands` have. A package of its own can add commands the same way.
"""
