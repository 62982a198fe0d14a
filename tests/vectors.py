"""The protocol test vectors, shipped with the tests in ``tests/data/vectors.json``.

They are the 50 example frames printed in the three manuals (byte for byte, mismatched
checksums included, with ``request_hex_corrected``) plus 13 frames built from the
documented layouts (``"synthesized": true``); docs/protocols.md explains every mismatch.
A missing or unreadable file is an error, never a skip: the file is part of the repository.
"""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path
from typing import Any

VECTORS_PATH = Path(__file__).resolve().parent / "data" / "vectors.json"


@cache
def _all() -> tuple[dict[str, Any], ...]:
    try:
        text = VECTORS_PATH.read_text(encoding="utf-8")
    except OSError as e:
        raise RuntimeError(f"test vectors missing: cannot read {VECTORS_PATH}: {e}") from e
    vectors: list[dict[str, Any]] = json.loads(text)["vectors"]
    if not vectors:
        raise RuntimeError(f"test vectors: {VECTORS_PATH} holds no vectors")
    return tuple(vectors)


def load_vectors() -> list[dict[str, Any]]:
    """Every vector (a fresh list; the dicts are shared, do not modify them)."""
    return list(_all())


def vectors_of(device_kind: str) -> list[dict[str, Any]]:
    """The vectors of one device kind; raises if the kind has none (a typo, or a lost file)."""
    found = [v for v in _all() if v["device_kind"] == device_kind]
    if not found:
        kinds = sorted({v["device_kind"] for v in _all()})
        raise ValueError(f"device_kind={device_kind!r} has no vectors: allowed {kinds}")
    return found
