"""Errors raised by kpi.

Contract: every bad input to kpi -- a missing or unreadable file, a crop box outside the
image, a load-cell record with NaNs or a time axis that runs backwards, a config value out of
range, an image in which no heap or no edge can be found -- raises :class:`KPIInputError`.
Its message starts with where the input came from (a file path, a config class and field, or a
function argument) and then names the bad value and what was expected, so a lab user can fix
the input without reading the source::

    loadcell.csv: column 'time_s' is not increasing at row 17 (t=0.34 s after t=0.36 s)

``KPIInputError`` subclasses ``ValueError`` so callers that already catch ``ValueError`` keep
working.
"""
from __future__ import annotations


class KPIInputError(ValueError):
    """An image, load-cell record, crop box or config value that kpi cannot measure."""


def bad_input(source: str, problem: str) -> KPIInputError:
    """Build the standard error: ``<source>: <problem>``."""
    return KPIInputError(f"{source}: {problem}")


def out_of_range(source: str, name: str, value, allowed: str) -> KPIInputError:
    """Build the standard range error: ``<source>: <name> = <value> is not allowed; expected <allowed>``."""
    return KPIInputError(f"{source}: {name} = {value!r} is not allowed; expected {allowed}")
