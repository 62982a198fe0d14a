"""The rig report (issue 41): a failed run says so at the top in red (case 1), and the
plots are legible (case 7): every label inside the image, legends off the data, a
histogram's count axis in whole numbers from 0.  Built from a synthetic run whose
figures come from the analysis, so no bus is needed."""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from motorbus.rig.analysis import Sample, repeat_figures, step_figures, track_figures
from motorbus.rig.plan import RigPlan
from motorbus.rig.report import write_report
from motorbus.rig.runner import DeviceResult, RigResult

SVG = "{http://www.w3.org/2000/svg}"
#: Width of a label's character, in em: DejaVu Sans's digits (what Debian's chromium
#: draws ``system-ui`` with) are 0.636 em; narrower fonts only help.
CHAR_EM = 0.64


def synthetic_run() -> RigResult:
    """A 550 -> 1450 step at 1000 units/s written at 0.5 s, a 1 Hz sine lagging 40 ms
    from 4 s to 7 s, 40 latencies of 29..41 ms and ten repeat approaches."""
    samples = [Sample(k / 1000, 550.0 + max(0.0, min(900.0, (k - 512) * 1.0))) for k in range(3000)]
    step = step_figures(samples, 0.5, 550.0, 1450.0)
    times = [4 + k / 100 for k in range(300)]
    targets = [1000 + 200 * math.sin(2 * math.pi * t) for t in times]
    wave = [
        Sample(4 + k / 1000, 1000 + 200 * math.sin(2 * math.pi * (4 + k / 1000 - 0.04)))
        for k in range(3000)
    ]
    track = track_figures(times, targets, wave, frequency_hz=1.0)
    below, above = [998.0, 998.2, 997.9, 998.1, 998.0], [1002.0, 1002.1, 1001.9, 1002.0, 1002.2]
    device = DeviceResult(
        1,
        steps=[step],
        tracks=[track],
        track_windows=[(times[0], times[-1])],
        dead_times_ms=[29.0 + (k * 7 % 13) for k in range(40)],
        repeat=repeat_figures(1000.0, below, above),
        ends={"below": below, "above": above},
    )
    return RigResult(
        plan=RigPlan(ids=(1,), frequencies=(1.0,)),
        devices={1: device},
        samples={1: samples + wave},
        targets={1: [(0.5, 1450), *((t, round(x)) for t, x in zip(times, targets, strict=True))]},
        started=0.0,
        seconds=12.0,
        polls=6000,
        poll_timeouts=0,
    )


def svgs(page: str) -> dict[str, ET.Element]:
    """Every plot of the page by its title (aria-label)."""
    out = {}
    for chunk in re.findall(r"<svg .*?</svg>", page, flags=re.S):
        root = ET.fromstring(chunk)
        out[root.attrib["aria-label"]] = root
    return out


def extent(text: ET.Element) -> tuple[float, float]:
    """The horizontal extent of an unrotated label."""
    x = float(text.attrib["x"])
    w = len("".join(text.itertext())) * float(text.attrib.get("font-size", "16")) * CHAR_EM
    anchor = text.attrib.get("text-anchor", "start")
    left = x - w / 2 if anchor == "middle" else x - w if anchor == "end" else x
    return left, left + w


@pytest.fixture(scope="module")
def page(tmp_path_factory: pytest.TempPathFactory) -> str:
    paths = write_report(tmp_path_factory.mktemp("report"), synthetic_run())
    return paths["report"].read_text(encoding="utf-8")


def test_every_plot_label_is_inside_its_image(page: str) -> None:
    plots = svgs(page)
    assert len(plots) >= 5
    for title, svg in plots.items():
        width = float(svg.attrib["width"])
        for text in svg.iter(f"{SVG}text"):
            if "transform" in text.attrib:
                continue  # the rotated y label: it is laid out along the left edge
            left, right = extent(text)
            assert left >= 0 and right <= width, (title, "".join(text.itertext()), left, right)


def test_legends_are_off_the_data(page: str) -> None:
    plots = svgs(page)
    for title, labels in (
        ("Tracking at 1 Hz (its last stretch)", {"target", "position"}),
        ("Step response", {"550 → 1450"}),
        ("Repeatability: where each approach ended", {"from below", "from above"}),
    ):
        svg = plots[title]
        frame = next(r for r in svg.iter(f"{SVG}rect") if r.attrib.get("fill") == "none")
        top = float(frame.attrib["y"])
        found = set()
        for text in svg.iter(f"{SVG}text"):
            label = "".join(text.itertext())
            if label in labels and "transform" not in text.attrib:
                found.add(label)
                # A label's baseline at y: its glyphs stand above it; all above the frame.
                assert float(text.attrib["y"]) <= top - 2, (title, label)
        assert found == labels, title


def test_the_latency_histogram_counts_in_whole_numbers_from_zero(page: str) -> None:
    svg = svgs(page)["Latency (dead time) histogram"]
    frame = next(r for r in svg.iter(f"{SVG}rect") if r.attrib.get("fill") == "none")
    left = float(frame.attrib["x"])
    ticks = [
        "".join(t.itertext())
        for t in svg.iter(f"{SVG}text")
        if t.attrib.get("text-anchor") == "end" and float(t.attrib["x"]) < left
    ]
    assert ticks, "no count ticks"
    values = [float(t) for t in ticks]
    assert all(re.fullmatch(r"\d+", t) for t in ticks), ticks
    assert min(values) == 0
    assert max(values) >= 4  # the tallest bin: 40 values over 13 distinct ms, one 4 times


def test_a_passed_run_says_so_at_the_top(page: str) -> None:
    top = page[: page.index("<h2>")]
    assert 'class="verdict passed"' in top and "PASSED" in top


def test_a_failed_run_says_so_at_the_top_in_red(tmp_path: Path) -> None:
    from motorbus.rig.runner import Failure

    result = synthetic_run()
    why = "did not follow: sent from 0 to 550, it did not move (at 0 after 5.0 s)"
    result.devices[1].failures.append(Failure(1, "step", why))
    page = write_report(tmp_path, result)["report"].read_text(encoding="utf-8")
    top = page[: page.index("<h2>")]
    assert 'class="verdict failed"' in top
    assert f"la:1 step: {why}" in top
    css = re.search(r"\.verdict\.failed\{([^}]*)\}", page)
    assert css is not None and "color:#b00020" in css.group(1)
    doc = (tmp_path / "results.json").read_text(encoding="utf-8")
    assert '"passed": false' in doc and '"test": "step"' in doc
