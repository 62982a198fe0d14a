"""Write a rig run to a folder: ``results.json``, ``samples.csv`` and ``report.html``.

The HTML report is one self-contained file: plots are inline SVG drawn here (no
script, no stylesheet or font from the network), so it opens anywhere, offline, and
can be attached to a ticket.
"""

from __future__ import annotations

import csv
import html
import itertools
import json
import math
import platform
import socket
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from motorbus.rig.analysis import Sample
from motorbus.rig.runner import DeviceResult, RigResult

__all__ = ["results_document", "write_report"]

_COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b")


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("motorbus")
    except PackageNotFoundError:
        return "unknown"


def _clean(value: Any) -> Any:
    """JSON has no NaN: a figure that could not be measured is null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    return value


def results_document(result: RigResult, bus_stats: dict[str, Any] | None = None) -> dict[str, Any]:
    """The content of ``results.json``."""
    doc: dict[str, Any] = _clean(
        {
            "format": "motorbus-rig-results",
            "version": 1,
            "motorbus": _version(),
            "host": {
                "name": socket.gethostname(),
                "python": platform.python_version(),
                "platform": platform.platform(),
            },
            "started_unix": result.started,
            "seconds": result.seconds,
            "plan": result.plan.as_dict(),
            "aborted": result.aborted,
            "passed": result.passed,
            "failures": [f.as_dict() for f in result.failures]
            + [
                {"device": f"la:{i}", "test": None, "why": "not tested: the run was aborted"}
                for i in result.untested
            ],
            "sampling": {
                **result.sampling(),
                "polls": result.polls,
                "poll_timeouts": result.poll_timeouts,
            },
            "bus": bus_stats or {},
            "devices": {f"la:{i}": d.figures() for i, d in result.devices.items()},
            "details": {f"la:{i}": d.details() for i, d in result.devices.items()},
        }
    )
    return doc


def _write_samples(path: Path, result: RigResult) -> None:
    t0 = min((s[0].t for s in result.samples.values() if s), default=0.0)
    with path.open("w", newline="", encoding="utf-8") as f:
        out = csv.writer(f)
        out.writerow(["t_s", "id", "target", "position", "current_ma", "force_g"])
        for ident, samples in result.samples.items():
            targets = result.targets[ident]
            k = 0
            target: int | str = ""
            for s in samples:
                while k < len(targets) and targets[k][0] <= s.t:
                    target = targets[k][1]
                    k += 1
                out.writerow(
                    [
                        f"{s.t - t0:.6f}",
                        ident,
                        target,
                        f"{s.position:g}",
                        f"{s.current:g}",
                        f"{s.force:g}",
                    ]
                )


# -- SVG ------------------------------------------------------------------------------

#: Width of a character of the plots' labels, in em: an upper bound for digits and
#: Latin text in the sans-serif fonts browsers use (labels are laid out with it).
_CHAR_EM = 0.62
_TICK_FONT, _LABEL_FONT, _TITLE_FONT = 10, 11, 13


def _text_width(text: str, size: int) -> float:
    return len(text) * size * _CHAR_EM


def _nice_ticks(lo: float, hi: float, count: int = 5, *, integer: bool = False) -> list[float]:
    """About ``count`` round ticks (1, 2 or 5 times a power of ten apart) covering
    ``lo..hi``: the first at or below ``lo``, the last at or above ``hi``."""
    if hi <= lo:
        lo, hi = lo - 1.0, hi + 1.0
    raw = (hi - lo) / max(1, count - 1)
    power = 10 ** math.floor(math.log10(raw))
    step = next(m * power for m in (1, 2, 5, 10) if m * power >= raw)
    if integer:
        step = max(1.0, round(step))
    first = math.floor(lo / step + 1e-9) * step
    last = math.ceil(hi / step - 1e-9) * step
    n = round((last - first) / step)
    return [first + k * step for k in range(n + 1)]


def _log_ticks(lo: float, hi: float) -> list[float]:
    """Ticks at 1, 2 and 5 times the powers of ten inside ``lo..hi`` (both > 0)."""
    ticks = [
        m * 10.0**e
        for e in range(math.floor(math.log10(lo)), math.ceil(math.log10(hi)) + 1)
        for m in (1, 2, 5)
    ]
    inside = [t for t in ticks if lo * (1 - 1e-9) <= t <= hi * (1 + 1e-9)]
    return inside or [lo, hi]


def _tick_text(value: float, ticks: Sequence[float]) -> str:
    """A tick's label with as many decimals as the tick spacing needs (no "0.30000004")."""
    if len(ticks) > 1:
        step = min(abs(b - a) for a, b in itertools.pairwise(ticks)) or 1.0
        decimals = max(0, -math.floor(math.log10(step) + 1e-9))
    else:
        decimals = 3
    text = f"{value:.{decimals}f}"
    return "0" if float(text) == 0 else text


def _svg(
    title: str,
    series: Sequence[tuple[str, Sequence[tuple[float, float]], str]],
    xlabel: str,
    ylabel: str,
    *,
    width: int = 640,
    height: int = 260,
    logx: bool = False,
    integer_x: bool = False,
    integer_y: bool = False,
    bar_width: float = 0.0,
    x_pad: float = 0.0,
) -> str:
    """A chart: ``series`` are (label, points, "line" | "points" | "bars").

    Legible by construction: round ticks with labels that fit inside the image (the
    margins are sized from the labels), the legend above the plot area (never over the
    data), and ``integer_y`` (counts) gives whole ticks from 0.  ``bar_width`` is the
    width of a bar in x units (a histogram's bin); ``x_pad`` widens the x axis by
    that many units at each end (points off the frame)."""
    pts = [p for _, ps, _ in series for p in ps if all(math.isfinite(v) for v in p)]
    if logx:
        pts = [p for p in pts if p[0] > 0]
    if not pts:
        return f"<figure><figcaption>{html.escape(title)}: no data</figcaption></figure>"
    xs = [x for x, _ in pts]
    ys = [y for _, y in pts]
    half_bar = bar_width / 2
    x_lo, x_hi = min(xs) - half_bar, max(xs) + half_bar
    if logx:
        xticks = _log_ticks(x_lo, x_hi)
        x0, x1 = math.log10(min(x_lo, xticks[0])), math.log10(max(x_hi, xticks[-1]))
        if x1 == x0:
            x0, x1 = x0 - 0.5, x1 + 0.5
    else:
        # The x axis spans the data (time series start where they start); its ticks
        # are the round values inside it.
        x0, x1 = x_lo - x_pad, x_hi + x_pad
        if x1 <= x0:
            x0, x1 = x0 - 1.0, x1 + 1.0
        span = x1 - x0
        xticks = [x0, x1]
        for count in (5, 8, 12):  # at least 4 ticks inside the data when they fit
            inside = [
                t
                for t in _nice_ticks(x0, x1, count, integer=integer_x)
                if x0 - 1e-9 * span <= t <= x1 + 1e-9 * span
            ]
            if len(inside) >= 2:
                xticks = inside
            if len(inside) >= 4:
                break
    y_lo, y_hi = min(ys), max(ys)
    if integer_y:
        y_lo = min(0.0, y_lo)
    yticks = _nice_ticks(y_lo, y_hi, integer=integer_y)
    y0, y1 = yticks[0], yticks[-1]
    xtexts = [f"{t:g}" if logx else _tick_text(t, xticks) for t in xticks]
    ytexts = [_tick_text(t, yticks) for t in yticks]

    # Margins from the labels: the y tick labels and the rotated y label on the left,
    # half of the last x tick label on the right, the title and the legend on top.
    left = 6 + _LABEL_FONT + 8 + max(_text_width(t, _TICK_FONT) for t in ytexts) + 6
    right = max(12.0, _text_width(xtexts[-1], _TICK_FONT) / 2 + 4)
    legend = [(label, _COLORS[n % len(_COLORS)]) for n, (label, _, _) in enumerate(series)]
    legend_w = sum(22 + _text_width(label, _LABEL_FONT) + 12 for label, _ in legend)
    title_w = _text_width(title, _TITLE_FONT)
    two_rows = left + title_w + 16 + legend_w > width - right
    top = 46 if two_rows else 28
    bottom = 40
    pw, ph = width - left - right, height - top - bottom

    def px(x: float) -> float:
        v = math.log10(x) if logx else x
        return left + (v - x0) / (x1 - x0) * pw

    def py(y: float) -> float:
        return top + (1 - (y - y0) / (y1 - y0)) * ph

    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
        f'role="img" aria-label="{html.escape(title)}">',
        f'<text x="{left:.1f}" y="17" font-size="{_TITLE_FONT}">{html.escape(title)}</text>',
        f'<text x="{left + pw / 2:.1f}" y="{height - 8}" font-size="{_LABEL_FONT}" '
        f'text-anchor="middle">{html.escape(xlabel)}</text>',
        f'<text x="{6 + _LABEL_FONT}" y="{top + ph / 2:.1f}" font-size="{_LABEL_FONT}" '
        f'transform="rotate(-90 {6 + _LABEL_FONT} {top + ph / 2:.1f})" text-anchor="middle">'
        f"{html.escape(ylabel)}</text>",
    ]
    for t, text in zip(yticks, ytexts, strict=True):
        y = py(t)
        parts.append(
            f'<line x1="{left:.1f}" y1="{y:.1f}" x2="{left + pw:.1f}" y2="{y:.1f}" '
            'stroke="#e6e6e6"/>'
            f'<text x="{left - 5:.1f}" y="{y + 3.5:.1f}" font-size="{_TICK_FONT}" '
            f'text-anchor="end">{text}</text>'
        )
    for t, text in zip(xticks, xtexts, strict=True):
        x = px(t)
        parts.append(
            f'<line x1="{x:.1f}" y1="{top + ph:.1f}" x2="{x:.1f}" y2="{top + ph + 4:.1f}" '
            'stroke="#999"/>'
            f'<text x="{x:.1f}" y="{top + ph + 15:.1f}" font-size="{_TICK_FONT}" '
            f'text-anchor="middle">{text}</text>'
        )
    parts.append(
        f'<rect x="{left:.1f}" y="{top}" width="{pw:.1f}" height="{ph}" fill="none" stroke="#999"/>'
    )
    for n, (_label, points, kind) in enumerate(series):
        color = _COLORS[n % len(_COLORS)]
        good = [(x, y) for x, y in points if math.isfinite(x) and math.isfinite(y)]
        if kind == "line" and len(good) > 1:
            path = " ".join(f"{px(x):.1f},{py(y):.1f}" for x, y in good)
            parts.append(
                f'<polyline fill="none" stroke="{color}" stroke-width="1.3" points="{path}"/>'
            )
        elif kind == "bars":
            base = py(max(y0, 0.0))
            for x, y in good:
                a, b = px(x - half_bar), px(x + half_bar)
                bar_w = max(1.0, b - a - 1)
                parts.append(
                    f'<rect x="{a + 0.5:.1f}" y="{min(py(y), base):.1f}" width="{bar_w:.1f}" '
                    f'height="{abs(base - py(y)):.1f}" fill="{color}"/>'
                )
        else:
            for x, y in good:
                parts.append(f'<circle cx="{px(x):.1f}" cy="{py(y):.1f}" r="2.5" fill="{color}"/>')
    # The legend: right-aligned on the title's line, or on its own line under it.
    x = width - right - legend_w
    y = (top - 8) if two_rows else 17
    for label, color in legend:
        parts.append(
            f'<g class="legend"><line x1="{x:.1f}" y1="{y - 4}" x2="{x + 16:.1f}" y2="{y - 4}" '
            f'stroke="{color}" stroke-width="3"/><text x="{x + 22:.1f}" y="{y}" '
            f'font-size="{_LABEL_FONT}" fill="{color}">{html.escape(label)}</text></g>'
        )
        x += 22 + _text_width(label, _LABEL_FONT) + 12
    parts.append("</svg>")
    return f'<figure class="plot">{"".join(parts)}</figure>'


def _window(samples: Sequence[Sample], t0: float, t1: float) -> list[tuple[float, float]]:
    return [((s.t - t0) * 1e3, s.position) for s in samples if t0 <= s.t <= t1]


def _table(rows: Sequence[Sequence[Any]], head: Sequence[str]) -> str:
    def cell(v: Any) -> str:
        if isinstance(v, float):
            return "n/a" if not math.isfinite(v) else f"{v:.4g}"
        return html.escape(str(v))

    out = ["<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>"]
    out += ["<tr>" + "".join(f"<td>{cell(v)}</td>" for v in row) + "</tr>" for row in rows]
    return "".join(out) + "</table>"


def _device_section(ident: int, d: DeviceResult, result: RigResult) -> str:
    samples = result.samples[ident]
    targets = result.targets[ident]
    parts = [f'<section id="la-{ident}"><h2>Actuator la:{ident}</h2>']
    if d.failures:
        parts.append(
            '<ul class="failed">'
            + "".join(f"<li>{html.escape(f'{f.test}: {f.why}')}</li>" for f in d.failures)
            + "</ul>"
        )
    figs = d.figures()
    parts.append(_table([(k, v) for k, v in figs.items()], ["figure", "value"]))
    if d.steps:
        series = []
        for s in d.steps:
            t_cmd = s.command_t
            if not math.isfinite(t_cmd):
                continue
            settle = s.settling_time_ms / 1e3 if math.isfinite(s.settling_time_ms) else 2.0
            points = _window(samples, t_cmd, t_cmd + settle + 0.2)
            series.append((f"{s.start:.0f} → {s.end:.0f}", points, "line"))
        parts.append(_svg("Step response", series, "ms from the target's write", "position"))
    if d.tracks:
        last = d.tracks[-1]
        f = last.response.frequency_hz if last.response else None
        if d.track_windows:
            t_first, t_end = d.track_windows[-1]
            t_start = max(t_first, t_end - (min(2.0, 2.0 / f) if f else 2.0))
            tgt = [((t - t_start) * 1e3, float(x)) for t, x in targets if t_start <= t <= t_end]
            pos = _window(samples, t_start, t_end)
            parts.append(
                _svg(
                    f"Tracking at {f:g} Hz (its last stretch)" if f else "Tracking",
                    [("target", tgt, "line"), ("position", pos, "line")],
                    "ms",
                    "position",
                )
            )
        bode = [t.response for t in d.tracks if t.response is not None]
        if bode:
            parts.append(
                _table(
                    [
                        (
                            b.frequency_hz,
                            b.amplitude_ratio,
                            20 * math.log10(b.amplitude_ratio)
                            if b.amplitude_ratio > 0
                            else math.nan,
                            b.phase_deg,
                            t.lag_ms,
                            t.rms_error,
                        )
                        for b, t in zip(bode, d.tracks, strict=False)
                    ],
                    ["Hz", "amplitude ratio", "gain dB", "phase deg", "lag ms", "rms error"],
                )
            )
            parts.append(
                _svg(
                    "Bode: gain",
                    [
                        (
                            "gain dB",
                            [
                                (b.frequency_hz, 20 * math.log10(max(b.amplitude_ratio, 1e-9)))
                                for b in bode
                            ],
                            "line",
                        )
                    ],
                    "Hz",
                    "dB",
                    logx=True,
                )
            )
            parts.append(
                _svg(
                    "Bode: phase",
                    [("phase", [(b.frequency_hz, b.phase_deg) for b in bode], "line")],
                    "Hz",
                    "degrees",
                    logx=True,
                )
            )
    if d.dead_times_ms:
        finite = [v for v in d.dead_times_ms if math.isfinite(v)]
        if finite:
            lo, hi = min(finite), max(finite)
            bins = 20
            width = (hi - lo) / bins or 1.0
            counts = [0] * bins
            for v in finite:
                counts[min(bins - 1, int((v - lo) / width))] += 1
            hist = [(lo + (k + 0.5) * width, float(c)) for k, c in enumerate(counts)]
            parts.append(
                _svg(
                    "Latency (dead time) histogram",
                    [("small steps", hist, "bars")],
                    "dead time, ms",
                    "count",
                    integer_y=True,
                    bar_width=width,
                )
            )
    if d.repeat is not None:
        r = d.repeat
        parts.append(
            _svg(
                "Repeatability: where each approach ended",
                [
                    (
                        "from below",
                        [(k + 1.0, v) for k, v in enumerate(d.ends.get("below", []))],
                        "points",
                    ),
                    (
                        "from above",
                        [(k + 1.0, v) for k, v in enumerate(d.ends.get("above", []))],
                        "points",
                    ),
                ],
                "approach",
                f"position (target {r.target:g})",
                integer_x=True,
                x_pad=0.5,
            )
        )
    parts.append("</section>")
    return "".join(parts)


_CSS = """
body{font-family:system-ui,sans-serif;margin:1.5em;max-width:70em;color:#222}
table{border-collapse:collapse;margin:.6em 0}td,th{border:1px solid #ccc;padding:2px 8px;
text-align:right}th{background:#f3f3f3}figure{margin:.6em 0}h2{margin-top:1.6em}
.verdict{padding:.6em 1em;border-radius:4px;font-weight:600}
.verdict.failed{background:#fde8e8;color:#b00020;border:2px solid #b00020}
.verdict.passed{background:#e8f5e9;color:#1b5e20;border:1px solid #1b5e20}
.verdict ul{margin:.3em 0 0;font-weight:normal}ul.failed{color:#b00020}
"""


def _verdict(result: RigResult) -> str:
    """The run's verdict, first thing on the page: red with every failure, or green."""
    if result.passed:
        n = len(result.plan.ids)
        return (
            f'<div class="verdict passed">PASSED: {n} actuator{"s" if n > 1 else ""}, '
            f"every test of the plan ({', '.join(result.plan.tests)}) measured.</div>"
        )
    items = [str(f) for f in result.failures]
    items += [f"la:{i}: not tested (the run was aborted first)" for i in result.untested]
    return (
        '<div class="verdict failed">FAILED: '
        + ("the run was aborted" if result.aborted else "the rig does not vouch for this run")
        + "<ul>"
        + "".join(f"<li>{html.escape(t)}</li>" for t in items)
        + "</ul></div>"
    )


def write_report(
    out: Path, result: RigResult, bus_stats: dict[str, Any] | None = None
) -> dict[str, Path]:
    """Write ``results.json``, ``samples.csv`` and ``report.html`` into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    doc = results_document(result, bus_stats)
    paths = {
        "results": out / "results.json",
        "samples": out / "samples.csv",
        "report": out / "report.html",
    }
    paths["results"].write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    _write_samples(paths["samples"], result)
    sampling = doc["sampling"]
    body = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        "<meta name='viewport' content='width=device-width, initial-scale=1'>",
        f"<title>motorbus rig report</title><style>{_CSS}</style></head><body>",
        "<h1>motorbus rig report</h1>",
        _verdict(result),
        f"<p>motorbus {html.escape(doc['motorbus'])} on {html.escape(doc['host']['name'])} "
        f"({html.escape(doc['host']['platform'])}, Python {html.escape(doc['host']['python'])}); "
        f"{result.seconds:.1f} s.</p>",
    ]
    body.append("<h2>Plan</h2>")
    body.append(
        _table([(k, str(v)) for k, v in result.plan.as_dict().items()], ["setting", "value"])
    )
    body.append("<h2>Sampling and bus</h2>")
    body.append(
        _table(
            [(k, v) for k, v in sampling.items()]
            + [
                (f"bus.{k}", v)
                for k, v in (bus_stats or {}).items()
                if not isinstance(v, dict | list)
            ],
            ["figure", "value"],
        )
    )
    for ident, d in result.devices.items():
        body.append(_device_section(ident, d, result))
    body.append("</body></html>\n")
    paths["report"].write_text("".join(body), encoding="utf-8")
    return paths
