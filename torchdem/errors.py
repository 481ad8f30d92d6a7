"""Errors raised by torchdem.

Contract: every error that reports bad input names the bad value, the allowed range and
where the value came from (a config key, a file, or the argument of a function), so a user
can fix it without reading the source.
"""
from __future__ import annotations

import os
import sys
from typing import Callable, TypeVar

T = TypeVar("T")


class ConfigError(ValueError):
    """A parameter, config value or input tensor is outside its allowed range."""


def out_of_range(name: str, value, allowed: str, source: str) -> ConfigError:
    """Build the standard bad-input error: ``<source>: <name> = <value> is outside <allowed>``."""
    return ConfigError(f"{source}: {name} = {value!r} is not allowed; expected {allowed}")


class BlowUpError(RuntimeError):
    """A simulation became unphysical (NaN, runaway speed, energy growth).

    Attributes:
        step: the time step index at which the guard fired.
        member: the ensemble member (index along B) that blew up.
        cause: a short description of what was detected and the likely cause.
    """

    def __init__(self, step: int, member: int, cause: str):
        self.step = step
        self.member = member
        self.cause = cause
        super().__init__(f"simulation blew up at step {step} in ensemble member {member}: {cause}")


def user_errors() -> tuple[type[BaseException], ...]:
    """Errors that mean bad input (a config value, a data file, an image), not a bug."""
    from kpi.errors import KPIInputError

    return (ConfigError, KPIInputError, FileNotFoundError)


def exit_on_bad_input(command: str, run: Callable[[], T]) -> T:
    """``run()``; bad input (:func:`user_errors`) ends the program with one line,
    ``<command>: error: <message>`` on stderr, and exit status 2 instead of a traceback, as every
    command and script of the project ends (``HYDRA_FULL_ERROR=1`` re-raises: the traceback).
    A script ends with ``if __name__ == "__main__": exit_on_bad_input("name.py", main)``."""
    try:
        return run()
    except user_errors() as exc:
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise
        message = " ".join(str(exc).split())
        print(f"{command}: error: {message}", file=sys.stderr, flush=True)
        sys.exit(2)
