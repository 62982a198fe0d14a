"""Device specs for the simulator command line: ``"la:1-15"`` -> fifteen ``LAModel``.

Accepted forms (options are ``key=value`` items of the model's constructor):

* ``la`` (ID 1), ``la:3``, ``la:1-15``, ``la:1,4,7``, ``la:1-3,write_reply=ack``
* ``project-stepper``, ``project-stepper:motor=3``
* ``quad-stepper``, ``quad-stepper:run_ack_address=motor``

Model modules are imported when a spec names them, so this module stays light.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Iterable, Sequence

from motorbus.errors import LocalProtocolError
from motorbus.protocol.base import Family
from motorbus.protocol.families import (
    LA_DEFAULT_BAUD,
    LA_ID_MAX,
    LA_ID_MIN,
    SPEC_NAMES,
    STEPPER_DEFAULT_BAUD,
    default_bus_baud,
)
from motorbus.protocol.ids import IdListError, parse_id_items
from motorbus.sim.model import DeviceModel

__all__ = [
    "DEVICE_KINDS",
    "LA_DEFAULT_BAUD",
    "LA_ID_MAX",
    "LA_ID_MIN",
    "STEPPER_DEFAULT_BAUD",
    "default_baud",
    "parse_device_spec",
    "parse_device_specs",
]

#: Spec names, in the order the help text lists them.
DEVICE_KINDS = SPEC_NAMES

_FORMS = (
    "la, la:ID, la:FIRST-LAST, la:ID,ID,... (IDs 1..254, optional key=value items), "
    "project-stepper[:key=value,...], quad-stepper[:key=value,...]"
)


def _factory(kind: str) -> Callable[..., DeviceModel]:
    # Imported here: a spec naming one family should not need the others' modules.
    if kind == "la":
        from motorbus.sim.la import LAModel

        return LAModel
    if kind == "project-stepper":
        from motorbus.sim.project_stepper import ProjectStepperModel

        return ProjectStepperModel
    from motorbus.sim.quad_stepper import QuadStepperModel

    return QuadStepperModel


def _bad(spec: str, why: str) -> LocalProtocolError:
    return LocalProtocolError(
        f"device spec {spec!r}: {why}; accepted forms: {_FORMS}", field="device", value=spec
    )


def _convert(spec: str, key: str, text: str, default: object) -> object:
    """Convert option text to the type of the constructor default (if any)."""
    try:
        if isinstance(default, bool):
            if text.lower() in ("1", "true", "yes", "on"):
                return True
            if text.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError(f"{text!r} is not a boolean")
        if isinstance(default, int):
            return int(text, 0)
        if isinstance(default, float):
            return float(text)
        if isinstance(default, str):
            return text
        if default is None:
            for conv in (lambda t: int(t, 0), float):
                try:
                    return conv(text)
                except ValueError:
                    continue
            return text
        return text
    except ValueError as err:
        raise _bad(spec, f"option {key}={text!r} is not valid ({err})") from err


def _options(
    spec: str, factory: Callable[..., DeviceModel], items: Iterable[str], reserved: Sequence[str]
) -> dict[str, object]:
    params = inspect.signature(factory).parameters
    accepted = [n for n, p in params.items() if p.kind is p.KEYWORD_ONLY and n not in reserved]
    accepted += [
        n for n, p in params.items() if p.kind is p.POSITIONAL_OR_KEYWORD and n not in reserved
    ]
    out: dict[str, object] = {}
    for item in items:
        key, _, text = item.partition("=")
        key = key.strip().replace("-", "_")
        if key not in accepted:
            listed = ", ".join(sorted(accepted)) or "none"
            raise _bad(spec, f"unknown option {key!r} (options of this device: {listed})")
        default = params[key].default
        out[key] = _convert(
            spec, key, text.strip(), None if default is inspect.Parameter.empty else default
        )
    return out


def _la_ids(spec: str, items: Sequence[str]) -> list[int]:
    try:  # the shared grammar (protocol/ids.py)
        ids = parse_id_items(items)
    except IdListError as err:
        why = err.reason
        if err.problem == "reversed":
            why = f"range {err.item!r} runs backwards: {err.reason}"
        elif err.problem == "duplicate":
            why = f"{err.reason} (A2-12: IDs on one bus must be distinct)"
        raise _bad(spec, why) from None
    return ids or [LA_ID_MIN]


def parse_device_spec(spec: str) -> list[DeviceModel]:
    """Build the models one spec describes (see the module docstring for the forms).

    Args:
        spec: e.g. ``"la:1-15"`` or ``"project-stepper:motor=3"``.

    Returns:
        The models, in ID order as written.

    Raises:
        LocalProtocolError: an unknown kind, a bad ID or range, an unknown option or a
            value the model refuses; the message names the spec and the accepted forms.
    """
    kind, _, rest = spec.strip().partition(":")
    kind = kind.strip().lower().replace("_", "-")
    if kind not in DEVICE_KINDS:
        allowed = ", ".join(DEVICE_KINDS)
        raise _bad(spec, f"unknown device kind {kind!r} (allowed kinds: {allowed})")
    items = [i.strip() for i in rest.split(",") if i.strip()] if rest else []
    options = [i for i in items if "=" in i]
    plain = [i for i in items if "=" not in i]
    factory = _factory(kind)
    try:
        if kind == "la":
            kwargs = _options(spec, factory, options, reserved=("id",))
            return [factory(id=i, **kwargs) for i in _la_ids(spec, plain)]
        if plain:
            raise _bad(spec, f"{plain[0]!r} is not a key=value option")
        return [factory(**_options(spec, factory, options, reserved=()))]
    except LocalProtocolError as err:
        if err.field == "device":
            raise
        raise _bad(spec, str(err)) from err
    except (TypeError, ValueError) as err:
        raise _bad(spec, str(err)) from err


def parse_device_specs(specs: Iterable[str], *, distinct_ids: bool = True) -> list[DeviceModel]:
    """Build the models of several specs; refuse two LA models with the same ID (unless
    not ``distinct_ids``: actuators connected one at a time may share one).

    Raises:
        LocalProtocolError: see ``parse_device_spec``; also a duplicate LA ID across specs.
    """
    models: list[DeviceModel] = []
    seen: dict[int, str] = {}
    for spec in specs:
        for model in parse_device_spec(spec):
            model_id = getattr(model, "id", None)
            if model.family is Family.LA and isinstance(model_id, int) and distinct_ids:
                if model_id in seen:
                    raise _bad(spec, f"LA ID {model_id} is already used by {seen[model_id]!r}")
                seen[model_id] = spec
            models.append(model)
    if not models:
        raise LocalProtocolError(
            f"no device given; accepted forms: {_FORMS}", field="device", value=None
        )
    return models


def default_baud(models: Iterable[DeviceModel]) -> int:
    """Return the bus rate for ``models``: 921600 if all are LA actuators, else 9600 bit/s."""
    return default_bus_baud(m.family for m in models)
