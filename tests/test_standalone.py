"""The repository stands alone: nothing refers to files a user's clone does not have."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from tests import vectors

ROOT = Path(__file__).resolve().parents[1]

#: Mentions of the development workspace's notes beside the repository, which a clone or an
#: sdist does not have: their facts live in docs/protocols.md and docs/platform.md.
OUTSIDE = re.compile(
    r"\.\./shared|shared/protocols|shared/PLATFORM|\b(?:PLATFORM|PROTOCOLS|AMBIGUITIES)\.md\b"
)
#: Folders of a working tree that are not the project's files.
NOT_OURS = {".git", ".venv", "venv", "build", "dist", "__pycache__", ".hypothesis"}

AMBIGUITY_IDS = (
    [f"A0-{n:02d}" for n in range(1, 19)]
    + [f"A1-{n:02d}" for n in range(1, 11)]
    + [f"A2-{n:02d}" for n in range(1, 23)]
    + [f"V{n}" for n in range(1, 7)]
)


def project_files() -> list[Path]:
    """Tracked files in a git checkout; every file of the tree in an unpacked sdist."""
    git = shutil.which("git")
    if git and (ROOT / ".git").exists():
        out = subprocess.run(
            [git, "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True, timeout=60
        )
        return [ROOT / p for p in out.stdout.decode().split("\0") if p]
    return [
        p
        for p in ROOT.rglob("*")
        if p.is_file()
        and not NOT_OURS.intersection(p.relative_to(ROOT).parts)
        and not p.name.endswith(".egg-info")
    ]


def text_of(path: Path) -> str | None:
    try:
        data = path.read_bytes()
    except OSError:  # a tracked file deleted in the working tree
        return None
    if b"\0" in data[:8192]:
        return None  # binary (plots)
    return data.decode("utf-8", errors="replace")


def test_no_file_refers_to_notes_outside_the_repository() -> None:
    files = project_files()
    assert len(files) > 50, "found too few files to believe the scan"
    me = Path(__file__).resolve()
    hits = []
    for path in files:
        if path.resolve() == me:
            continue
        text = text_of(path)
        if text is None:
            continue
        for lineno, line in enumerate(text.splitlines(), 1):
            if OUTSIDE.search(line):
                hits.append(f"{path.relative_to(ROOT)}:{lineno}: {line.strip()}")
    assert not hits, "refer to docs/protocols.md or docs/platform.md instead:\n" + "\n".join(hits)


def test_the_pattern_catches_what_it_must() -> None:
    # Spelled in two pieces so that this file does not itself mention the path.
    outside = "../" + "shared/x"
    for bad in (f"see {outside}", "`shared/PLATFORM.md`", "PROTOCOLS.md C.6", "AMBIGUITIES.md"):
        assert OUTSIDE.search(bad), bad
    for fine in ("docs/protocols.md C.6", "docs/platform.md section 1", "a shared machine"):
        assert not OUTSIDE.search(fine), fine


def test_docs_named_anywhere_exist() -> None:
    named: set[str] = set()
    for path in project_files():
        text = text_of(path)
        if text is not None:
            named.update(re.findall(r"\bdocs/[\w.-]+\.md\b", text))
    assert {"docs/protocols.md", "docs/platform.md", "docs/hardware.md"} <= named
    missing = sorted(n for n in named if not (ROOT / n).is_file())
    assert not missing, f"named but not in the repository: {missing}"


def test_protocols_doc_resolves_every_ambiguity() -> None:
    text = (ROOT / "docs" / "protocols.md").read_text(encoding="utf-8")
    rows = {m.group(1) for m in re.finditer(r"^\| (A[0-2]-\d\d|V\d) \|", text, re.M)}
    missing = [i for i in AMBIGUITY_IDS if i not in rows]
    assert not missing, f"docs/protocols.md has no table row for {missing}"


def test_vectors_ship_with_the_tests() -> None:
    assert vectors.VECTORS_PATH == ROOT / "tests" / "data" / "vectors.json"
    every = vectors.load_vectors()
    assert len(every) == 63
    assert sum(not v["synthesized"] for v in every) == 50  # the manuals' own examples
    kinds = {v["device_kind"] for v in every}
    assert kinds == {"ffaa11_project_stepper", "ffaa9_4axis_stepper", "inspire_la_55aa"}
    assert all(vectors.vectors_of(k) for k in kinds)


def test_a_missing_vectors_file_is_an_error(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setattr(vectors, "VECTORS_PATH", tmp_path / "nowhere.json")
    vectors._all.cache_clear()
    try:
        with pytest.raises(RuntimeError, match="test vectors missing"):
            vectors.load_vectors()
    finally:
        vectors._all.cache_clear()


def test_an_unknown_device_kind_is_an_error() -> None:
    with pytest.raises(ValueError, match=r"device_kind='la' has no vectors: allowed \["):
        vectors.vectors_of("la")
