"""``motorbus decode``: in-process through ``main`` and as ``python -m motorbus``."""

from __future__ import annotations

import io
import json
import subprocess
import sys
from typing import Any

import pytest

from motorbus.cli.main import EXIT_USAGE, main
from motorbus.protocol.base import parse_hex
from tests.vectors import load_vectors
from tests.zygote import run_motorbus

FAMILY_OF_KIND = {
    "inspire_la_55aa": "la",
    "ffaa11_project_stepper": "project_stepper",
    "ffaa9_4axis_stepper": "quad_stepper",
}
STATUS_HEX = "AA 55 11 01 04 00 22 EB 03 DE 03 14 64 00 F4 00 01 08 07 0A 07 94"
MOVE_HEX = "55 AA 04 01 21 37 14 05 76"


def decode(capsys: pytest.CaptureFixture[str], *args: str) -> list[dict[str, Any]]:
    """Run ``motorbus decode --json ARGS`` in-process; return the JSON objects printed."""
    assert main(["decode", "--json", *args]) == 0
    out = capsys.readouterr().out
    return [json.loads(line) for line in out.splitlines()]


def run_module(*args: str, stdin: str = "") -> subprocess.CompletedProcess[str]:
    return run_motorbus(["decode", *args], input=stdin)


def vector_frames() -> list[tuple[str, str, str, dict[str, Any]]]:
    """(family, direction, hex, vector) for every frame the vectors hold."""
    out = []
    for v in load_vectors():
        family = FAMILY_OF_KIND[v["device_kind"]]
        out.append((family, "request", v.get("request_hex_corrected") or v["request_hex"], v))
        for key in ("expected_reply_hex", "reply_hex", "completion_reply_hex"):
            text = v.get(key)
            # The read-project vector gives only the first 6 of its 226 reply bytes.
            if text and len(parse_hex(text)) == v.get(
                "expected_reply_length", len(parse_hex(text))
            ):
                out.append((family, "reply", text, v))
    return out


def test_a_dump_header_alone_is_a_truncated_frame(capsys: pytest.CaptureFixture[str]) -> None:
    (obj,) = decode(capsys, "--family", "project_stepper", "FF AA 3E 01 00 00")
    assert (obj["kind"], obj["reason"]) == ("garbage", "truncated frame")


def test_project_finished_event_of_the_vectors(capsys: pytest.CaptureFixture[str]) -> None:
    (v,) = [x for x in load_vectors() if x.get("completion_event_hex")]
    (obj,) = decode(capsys, v["completion_event_hex"])
    assert (obj["kind"], obj["family"], obj["name"]) == (
        "event",
        "project_stepper",
        "ProjectFinished",
    )


# -- every vector, in-process ----------------------------------------------------------------


def test_every_vector_decodes_to_a_frame_of_its_family(capsys: pytest.CaptureFixture[str]) -> None:
    frames = vector_frames()
    assert len(frames) > 80
    for family, direction, text, v in frames:
        (obj,) = decode(capsys, "--family", family, text)
        where = (v["description"], text)
        assert obj["kind"] == "frame", where
        assert (obj["family"], obj["direction"]) == (family, direction), where
        assert obj["name"] != "Unknown", (where, obj)
        assert obj["hex"] == text, where
        assert {"kind", "family", "direction", "name", "fields", "hex"} <= obj.keys()
        check_key_fields(obj, v, direction)


def check_key_fields(obj: dict[str, Any], v: dict[str, Any], direction: str) -> None:
    """The fields the vector's ``decoded`` block states, where both name them alike."""
    decoded, fields = v["decoded"], obj["fields"]
    if v["device_kind"] == "inspire_la_55aa" and direction == "request":
        if obj["name"] == "Broadcast":
            expected = [
                {"id": t["id"], "position": t["target_position"]} for t in decoded["targets"]
            ]
            assert fields["entries"] == expected
            return
        assert fields["id"] == decoded["id"]
        if "value" in decoded and obj["name"] != "ReadRegister":
            key = "value" if obj["name"] == "WriteRegister" else "position"
            assert fields[key] == decoded["value"], v["description"]
    if obj["name"] == "Status":
        assert fields["target"] == decoded["target_position_u16"]
        assert fields["position"] == decoded["current_position_s16"]
        assert fields["force"] == 500
    if obj["name"] == "ReadReply" and "value" in decoded:
        assert fields["value"] == decoded["value"]
    if v["device_kind"] != "inspire_la_55aa" and direction == "request":
        for key in ("motor", "project", "total_steps", "subdivision", "step_angle_x100"):
            if key in decoded and key in fields:
                assert fields[key] == decoded[key], (v["description"], key)


def test_la_move_to_position_1300(capsys: pytest.CaptureFixture[str]) -> None:
    (obj,) = decode(capsys, MOVE_HEX)
    assert (obj["family"], obj["direction"], obj["name"]) == ("la", "request", "MoveTo")
    assert obj["fields"] == {"id": 1, "position": 1300, "reply": True}


def test_status_reply_target_1003(capsys: pytest.CaptureFixture[str]) -> None:
    (obj,) = decode(capsys, STATUS_HEX)
    assert (obj["family"], obj["direction"], obj["name"]) == ("la", "reply", "Status")
    assert obj["fields"]["target"] == 1003  # EB 03, not the prose's 1000 (V4)
    assert obj["fields"]["errors"] == []


def test_the_226_byte_dump_decodes_its_step(capsys: pytest.CaptureFixture[str]) -> None:
    (v,) = [
        x
        for x in load_vectors()
        if x.get("expected_reply_hex", "") and len(parse_hex(x["expected_reply_hex"])) == 226
    ]
    (obj,) = decode(capsys, "--family", "project_stepper", v["expected_reply_hex"])
    assert obj["name"] == "ProjectDump"
    (step,) = obj["fields"]["steps"]
    detail = v["decoded"]["steps_detail"][0]
    assert step["run_distance"] == detail["run_distance"] == 1
    assert step["direction"] == "REVERSE"
    assert step["start_hz"] == detail["start_freq_hz"] == 50
    assert step["accel_hz"] == detail["accel_decel_hz"] == 30
    assert step["speed_rpm"] == detail["speed_rpm"] == 100
    assert step["delay_ms"] == detail["delay_ms"] == 1000


def test_v3_documented_checksum_is_garbage_and_corrected_one_decodes(
    capsys: pytest.CaptureFixture[str],
) -> None:
    bad, good = decode(capsys, "55 AA 04 03 19 37 E8 03 28", "55 AA 04 03 19 37 E8 03 42")
    assert (bad["kind"], bad["name"], bad["hex"]) == (
        "garbage",
        "garbage",
        "55 AA 04 03 19 37 E8 03 28",
    )
    assert "bad checksum" in bad["reason"]
    assert (good["name"], good["fields"]) == ("Follow", {"id": 3, "position": 1000, "reply": False})


def test_mixed_stream_prints_frames_events_and_garbage(capsys: pytest.CaptureFixture[str]) -> None:
    stream = f"{MOVE_HEX} 12 34 56 FF AA 6E 01 01 00 00 00 00 00 19 EE DD 01 {STATUS_HEX}"
    objs = decode(capsys, stream)
    assert [(o["kind"], o["name"]) for o in objs] == [
        ("frame", "MoveTo"),
        ("garbage", "garbage"),
        ("frame", "SelectProject"),
        ("event", "ProjectFinished"),
        ("garbage", "garbage"),
        ("frame", "Status"),
    ]
    assert objs[1]["hex"] == "12 34 56" and objs[4]["hex"] == "01"
    assert objs[2]["family"] == "project_stepper"


def test_text_output_is_one_line_per_item(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["decode", MOVE_HEX, "00 01"]) == 0
    assert capsys.readouterr().out.splitlines() == [
        f"la request MoveTo id=1 position=1300 reply=True  [{MOVE_HEX}]",
        "garbage (garbage) 2 bytes  [00 01]",
    ]


def test_stdin_lines_may_split_frames(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(sys, "stdin", io.StringIO("55AA0401\n2137 1405\n76\nEE DD\n"))
    objs = decode(capsys)
    assert [o["name"] for o in objs] == ["MoveTo", "ProjectFinished"]
    assert objs[0]["fields"]["position"] == 1300


def test_family_tells_stepper_replies_apart(capsys: pytest.CaptureFixture[str]) -> None:
    (quad,) = decode(capsys, "--family", "quad_stepper", "FF AA 00 0C 01 01")
    (project,) = decode(capsys, "--family", "project_stepper", "FF AA 00 0C 01 01")
    assert (quad["family"], quad["name"], quad["fields"]["led"]) == ("quad_stepper", "Done", 1)
    assert (project["family"], project["name"]) == ("project_stepper", "Ack")


def test_direction_restricts_what_is_framed(capsys: pytest.CaptureFixture[str]) -> None:
    (obj,) = decode(capsys, "--direction", "reply", MOVE_HEX)
    assert obj["kind"] == "garbage"


def test_non_hex_exits_2_with_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["decode", "55 AA", "zz"]) == EXIT_USAGE
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.splitlines() == ["motorbus decode: hex input: 'zz' is not hexadecimal"]


# -- as a subprocess ---------------------------------------------------------------------------


@pytest.mark.parametrize("family", sorted(set(FAMILY_OF_KIND.values())))
@pytest.mark.parametrize("direction", ["request", "reply"])
def test_module_decodes_every_vector_of_a_family_from_stdin(family: str, direction: str) -> None:
    texts = [t for f, d, t, _ in vector_frames() if (f, d) == (family, direction)]
    proc = run_module(
        "--json", "--family", family, "--direction", direction, stdin="\n".join(texts) + "\n"
    )
    assert proc.returncode == 0, proc.stderr
    objs = [json.loads(line) for line in proc.stdout.splitlines()]
    assert [o["hex"] for o in objs] == texts
    assert all(o["kind"] == "frame" and o["name"] != "Unknown" for o in objs)
    assert {(o["family"], o["direction"]) for o in objs} == {(family, direction)}


def test_module_arguments_and_garbage() -> None:
    proc = run_module(MOVE_HEX, "AB", STATUS_HEX)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[0] == f"la request MoveTo id=1 position=1300 reply=True  [{MOVE_HEX}]"
    assert lines[1] == "garbage (garbage) 1 byte  [AB]"
    assert lines[2].startswith("la reply Status id=1 target=1003 position=990 ")


def test_module_non_hex_exits_2() -> None:
    proc = run_module(stdin="55 AA\n55 AA 0G\n")
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert proc.stderr.splitlines() == [
        "motorbus decode: line 2: hex input: '0G' is not hexadecimal"
    ]


def test_a_bad_checksum_shows_the_expected_value(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["decode", "55", "AA", "04", "01", "21", "37", "14", "05", "77"]) == 0
    assert "la checksum 77, expected 76" in capsys.readouterr().out
    (doc,) = decode(capsys, "FF AA 01 00 00 00 00 00 00 00 00", "--direction", "request")
    assert "checksum 00, expected AA" in doc["reason"]
