"""The served-bus payloads (``motorbus.serve.keys``): pure, every refusal names its field."""

from __future__ import annotations

import pytest

from motorbus.protocol import la, quad_stepper
from motorbus.protocol.base import Family
from motorbus.serve import keys as k


def test_keys_are_versioned_and_chunks_checked() -> None:
    assert k.bus_key("arm", "request") == "motorbus/v1/bus/arm/request"
    assert k.client_key("c-1") == "motorbus/v1/client/c-1"
    for bad in ("a/b", "*", "", "x" * 129, 3):
        with pytest.raises(k.PayloadError) as err:
            k.bus_key(bad, "request")  # type: ignore[arg-type]
        assert err.value.field == "bus"


def test_a_frame_decodes_to_its_command_for_the_buses_families_only() -> None:
    status = la.Control(3, la.ControlAction.QUERY_STATUS)
    assert k.decode_frame(status.encode(), [Family.LA]) == status
    run = quad_stepper.Run(2)
    assert k.decode_frame(run.encode(), [Family.QUAD_STEPPER]) == run
    with pytest.raises(k.PayloadError) as err:
        k.decode_frame(status.encode(), [Family.QUAD_STEPPER])
    assert err.value.field == "frame"
    with pytest.raises(k.PayloadError, match="not a request frame"):
        k.decode_frame(status.encode()[:-1] + b"\x00", [Family.LA])


def test_fields_are_typed_and_named() -> None:
    payload = k.decode_json(b'{"a": 1, "b": true, "c": "x", "h": "0a0b"}')
    assert k.field_of(payload, "a", int) == 1
    assert k.hex_field(payload, "h") == b"\x0a\x0b"
    with pytest.raises(k.PayloadError) as err:
        k.field_of(payload, "b", int)  # a bool is no int here
    assert (err.value.field, err.value.value) == ("b", True)
    with pytest.raises(k.PayloadError, match="no 'z'"):
        k.field_of(payload, "z", int)
    assert k.field_of(payload, "z", int, optional=True, default=5) == 5
    with pytest.raises(k.PayloadError, match="not UTF-8 JSON"):
        k.decode_json(b"{")
    with pytest.raises(k.PayloadError, match="JSON object"):
        k.decode_json(b"[]")


def test_error_payloads_carry_a_known_kind() -> None:
    out = k.error_payload("bad_payload", "m", field="frame", value="zz")
    assert out == {
        "ok": False,
        "error": "bad_payload",
        "message": "m",
        "field": "frame",
        "value": "zz",
    }
    with pytest.raises(ValueError):
        k.error_payload("oops", "m")
