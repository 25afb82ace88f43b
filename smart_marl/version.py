"""The package version (one place: the package, checkpoints and vocabulary files record it)."""

__version__ = "0.1.0"
