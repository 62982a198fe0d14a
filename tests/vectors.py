"""Access to the shared test vectors (../shared/protocols/vectors.json)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

VECTORS_PATH = Path(__file__).resolve().parents[1].parent / "shared" / "protocols" / "vectors.json"


def load_vectors() -> list[dict[str, Any]]:
    """Every vector; skips the calling test with a clear reason if the file is missing."""
    if not VECTORS_PATH.exists():
        pytest.skip(f"shared test vectors not found at {VECTORS_PATH}")
    data = json.loads(VECTORS_PATH.read_text(encoding="utf-8"))
    vectors: list[dict[str, Any]] = data["vectors"]
    return vectors


def vectors_of(device_kind: str) -> list[dict[str, Any]]:
    """The vectors of one device kind, or ``[]`` if the file is missing.

    For parametrising at collection time, where skipping is not possible yet: an empty
    list makes pytest report the test as skipped ("got empty parameter set").
    """
    if not VECTORS_PATH.exists():
        return []
    data = json.loads(VECTORS_PATH.read_text(encoding="utf-8"))
    return [v for v in data["vectors"] if v["device_kind"] == device_kind]
