"""The old home of what the commands share, kept so that its imports keep working.

It was split by concern: bus options and opening a bus (:mod:`motorbus.cli.bus_options`),
printing (:mod:`motorbus.cli.output`), ID arguments (:mod:`motorbus.cli.ids`) and option
values (:mod:`motorbus.cli.values`).  New code imports from those.
"""

from __future__ import annotations

from motorbus.cli.bus_options import (
    BACKEND_ENV,
    BAUD_ENV,
    BUS_ENV,
    BUS_FILE_ENV,
    CLI_HOST_MARGIN_S,
    ENV_VARS,
    LA_BAUD,
    PORT_ENV,
    STEPPER_BAUD,
    add_bus_options,
    add_guard_option,
    available_ports,
    open_bus,
    open_port,
    port_error,
    resolve_port,
)
from motorbus.cli.ids import add_ids_argument, check_ids, parse_id_args, parse_ids
from motorbus.cli.output import LiveText, add_json_option, plural, print_json, say
from motorbus.cli.values import MAX_SECONDS, STEP_ANGLE_SCALE, check_seconds, step_angle_x100

__all__ = [
    "BACKEND_ENV",
    "BAUD_ENV",
    "BUS_ENV",
    "BUS_FILE_ENV",
    "CLI_HOST_MARGIN_S",
    "ENV_VARS",
    "LA_BAUD",
    "MAX_SECONDS",
    "PORT_ENV",
    "STEPPER_BAUD",
    "STEP_ANGLE_SCALE",
    "LiveText",
    "add_bus_options",
    "add_guard_option",
    "add_ids_argument",
    "add_json_option",
    "available_ports",
    "check_ids",
    "check_seconds",
    "open_bus",
    "open_port",
    "parse_id_args",
    "parse_ids",
    "plural",
    "port_error",
    "print_json",
    "resolve_port",
    "say",
    "step_angle_x100",
]
