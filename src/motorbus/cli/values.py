"""Checks of option values the commands share: durations, step angles."""

from __future__ import annotations

import math

from motorbus.errors import LocalProtocolError
from motorbus.protocol.base import WAIT_TIMEOUT_MAX_S

__all__ = ["MAX_SECONDS", "STEP_ANGLE_SCALE", "check_seconds", "step_angle_x100"]

#: Longest duration any CLI option accepts, seconds: the library's (one day), a guard
#: against typos such as ``--timeout 1e9``, not a device limit.
MAX_SECONDS = WAIT_TIMEOUT_MAX_S


def check_seconds(field: str, value: float | None, lo: float = 0.0) -> float | None:
    """Return a duration option if it is a finite number in ``lo..MAX_SECONDS`` (or ``None``).

    Raises:
        LocalProtocolError: naming the option, the value and the allowed range.
    """
    if value is None:
        return None
    if not math.isfinite(value) or not lo <= value <= MAX_SECONDS:
        raise LocalProtocolError(
            f"{field}={value} is out of range: allowed {lo:g}..{MAX_SECONDS:g} s",
            field=field,
            value=value,
        )
    return value


#: Step angles are stored in 0.01 degree (doc 000 A.4 cmd 01, A0-09; doc 001 section 一).
STEP_ANGLE_SCALE = 100


def step_angle_x100(field: str, degrees: object, maximum: int) -> int:
    """Convert a step angle in degrees (e.g. 1.8) to the stored 0.01-degree integer (180).

    Args:
        field: the option or key named in errors.
        degrees: the angle in degrees, at most two decimals.
        maximum: the largest stored value (255 for both stepper families).

    Raises:
        LocalProtocolError: not a number, more than two decimals, or out of range.
    """
    if isinstance(degrees, bool) or not isinstance(degrees, (int, float)):
        raise LocalProtocolError(
            f"{field}={degrees!r} must be a number of degrees, e.g. 1.8", field=field
        )
    scaled = degrees * STEP_ANGLE_SCALE
    if not math.isfinite(scaled):
        raise LocalProtocolError(
            f"{field}={degrees} is out of range: allowed 0.01..{maximum / STEP_ANGLE_SCALE:g} "
            "degrees",
            field=field,
            value=degrees,
        )
    if abs(scaled - round(scaled)) > 1e-6:
        raise LocalProtocolError(
            f"{field}={degrees} is not a multiple of 0.01 degree (the stored resolution)",
            field=field,
            value=degrees,
        )
    x100 = round(scaled)
    if not 1 <= x100 <= maximum:
        raise LocalProtocolError(
            f"{field}={degrees} is out of range: allowed "
            f"{1 / STEP_ANGLE_SCALE}..{maximum / STEP_ANGLE_SCALE} degrees",
            field=field,
            value=degrees,
        )
    return x100
