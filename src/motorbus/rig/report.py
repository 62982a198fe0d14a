"""Write a rig run to a folder: ``results.json``, ``samples.csv`` and ``report.html``.

The HTML report is one self-contained file: plots are inline SVG drawn here (no
script, no stylesheet or font from the network), so it opens anywhere, offline, and
can be attached to a ticket.
"""

from __future__ import annotations

import csv
import html
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


def _svg(
    title: str,
    series: Sequence[tuple[str, Sequence[tuple[float, float]], str]],
    xlabel: str,
    ylabel: str,
    *,
    width: int = 640,
    height: int = 260,
    logx: bool = False,
) -> str:
    """A line/point chart: ``series`` are (label, points, "line" | "points" | "bars")."""
    pts = [p for _, ps, _ in series for p in ps if all(math.isfinite(v) for v in p)]
    if not pts:
        return f"<figure><figcaption>{html.escape(title)}: no data</figcaption></figure>"

    def fx(x: float) -> float:
        return math.log10(x) if logx else x

    xs = [fx(x) for x, _ in pts]
    ys = [y for _, y in pts]
    x0, x1 = min(xs), max(xs)
    y0, y1 = min(ys), max(ys)
    if x1 == x0:
        x0, x1 = x0 - 1, x1 + 1
    if y1 == y0:
        y0, y1 = y0 - 1, y1 + 1
    pad = 0.05 * (y1 - y0)
    y0, y1 = y0 - pad, y1 + pad
    left, right, top, bottom = 60, 10, 24, 36
    pw, ph = width - left - right, height - top - bottom

    def px(x: float) -> float:
        return left + (fx(x) - x0) / (x1 - x0) * pw

    def py(y: float) -> float:
        return top + (1 - (y - y0) / (y1 - y0)) * ph

    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
        f'role="img" aria-label="{html.escape(title)}">',
        f'<text x="{left}" y="16" font-size="13">{html.escape(title)}</text>',
        f'<rect x="{left}" y="{top}" width="{pw}" height="{ph}" fill="none" stroke="#999"/>',
        f'<text x="{left + pw / 2}" y="{height - 6}" font-size="11" text-anchor="middle">'
        f"{html.escape(xlabel)}</text>",
        f'<text x="12" y="{top + ph / 2}" font-size="11" transform="rotate(-90 12 {top + ph / 2})"'
        f' text-anchor="middle">{html.escape(ylabel)}</text>',
    ]
    for k in range(5):
        yv = y0 + (y1 - y0) * k / 4
        xv = x0 + (x1 - x0) * k / 4
        xlabel_v = 10**xv if logx else xv
        parts.append(
            f'<text x="{left - 4}" y="{py(yv) + 4:.1f}" font-size="10" '
            f'text-anchor="end">{yv:.4g}</text>'
        )
        parts.append(
            f'<text x="{left + pw * k / 4:.1f}" y="{top + ph + 14}" font-size="10" '
            f'text-anchor="middle">{xlabel_v:.4g}</text>'
        )
    for n, (label, points, kind) in enumerate(series):
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
                parts.append(
                    f'<line x1="{px(x):.1f}" y1="{base:.1f}" x2="{px(x):.1f}" y2="{py(y):.1f}" '
                    f'stroke="{color}" stroke-width="4"/>'
                )
        else:
            for x, y in good:
                parts.append(f'<circle cx="{px(x):.1f}" cy="{py(y):.1f}" r="2.5" fill="{color}"/>')
        parts.append(
            f'<text x="{left + 8 + 110 * n}" y="{top + 14}" font-size="11" fill="{color}">'
            f"{html.escape(label)}</text>"
        )
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
            series.append((f"{s.start:g} → {s.end:g}", points, "line"))
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
                _svg("Latency (dead time) histogram", [("count", hist, "bars")], "ms", "count")
            )
    if d.repeat is not None:
        r = d.repeat
        parts.append(
            _svg(
                "Repeatability: where each approach ended",
                [
                    (
                        "from below",
                        [(float(k), v) for k, v in enumerate(d.ends.get("below", []))],
                        "points",
                    ),
                    (
                        "from above",
                        [(float(k), v) for k, v in enumerate(d.ends.get("above", []))],
                        "points",
                    ),
                ],
                "approach",
                f"position (target {r.target:g})",
            )
        )
    parts.append("</section>")
    return "".join(parts)


_CSS = """
body{font-family:system-ui,sans-serif;margin:1.5em;max-width:70em;color:#222}
table{border-collapse:collapse;margin:.6em 0}td,th{border:1px solid #ccc;padding:2px 8px;
text-align:right}th{background:#f3f3f3}figure{margin:.6em 0}h2{margin-top:1.6em}
"""


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
        f"<p>motorbus {html.escape(doc['motorbus'])} on {html.escape(doc['host']['name'])} "
        f"({html.escape(doc['host']['platform'])}, Python {html.escape(doc['host']['python'])}); "
        f"{result.seconds:.1f} s.</p>",
    ]
    if result.aborted:
        body.append(f"<p><strong>Aborted:</strong> {html.escape(result.aborted)}</p>")
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
