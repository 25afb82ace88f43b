"""The environment's errors (environment stage): each is a :class:`smart_marl.errors.SmartMarlError`
and keeps the builtin base a caller of a Gym/PettingZoo environment would catch (``ValueError`` for
a bad argument or action, ``KeyError`` for an unknown agent, ``TypeError`` for a wrongly typed
argument, ``RuntimeError`` for a call out of order)."""

from __future__ import annotations

from smart_marl.errors import SmartMarlError


class EnvError(SmartMarlError):
    """Base of the environment's errors."""


class EnvConfigError(EnvError, ValueError):
    """A bad argument to the environment (scenes, prior, controlled agents, background...)."""


class EnvConfigTypeError(EnvConfigError, TypeError):
    """An argument to the environment of the wrong type."""


class UnknownAgentError(EnvError, KeyError):
    """An agent name that is not one of the episode's agents."""

    def __str__(self) -> str:  # KeyError's str() would quote the message
        return str(self.args[0]) if self.args else ""


class ActionError(EnvError, ValueError):
    """A missing action, or an action that is not a token id of the agent's vocabulary (NaN, inf,
    a fraction, out of range...)."""


class ActionTypeError(ActionError, TypeError):
    """Actions that are not a dict {agent name: token id}."""


class NoPriorLogitsError(EnvError, KeyError):
    """Prior logits asked of an environment that has no prior (``prior=None``)."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class EnvStateError(EnvError, RuntimeError):
    """A call the environment's state does not allow (step after the episode ended, render before reset)."""


__all__ = ["EnvError", "EnvConfigError", "EnvConfigTypeError", "UnknownAgentError", "ActionError", "ActionTypeError",
           "NoPriorLogitsError", "EnvStateError"]
