"""``StreamStats``: a line of text to print, a dict to store."""

from __future__ import annotations

from motorbus.streams import StreamStats


def test_summary_is_text_and_as_dict_has_the_same_figures() -> None:
    stats = StreamStats(ticks=300, late=2, skipped=1, frames=300, polls=40)
    stats.jitter.record(20e-6)
    text = stats.summary()
    assert isinstance(text, str)
    assert text.startswith("300 ticks (300 frames), 2 late, 1 skipped, 0 slipped; polls 40")
    d = stats.as_dict()
    assert (d["ticks"], d["late"], d["skipped"], d["polls"]) == (300, 2, 1, 40)
    assert d["jitter_max_us"] > 0
