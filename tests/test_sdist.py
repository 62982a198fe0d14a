"""The sdist is complete: built from this tree, unpacked elsewhere, it holds the tests, data,
docs, examples and benchmarks and the right metadata (its tests pass: test_interpreters.py)."""

from __future__ import annotations

import email.parser
from pathlib import Path

import pytest

from tests import packaging

pytestmark = [
    pytest.mark.timeout(300),
    pytest.mark.skipif(
        not packaging.build_available(), reason="the 'build' front-end is not installed"
    ),
]

#: Files a user who downloads the sdist needs to run the tests, examples and benchmarks.
REQUIRED = (
    "LICENSE",
    "README.md",
    "pyproject.toml",
    ".ci/run",
    "mkdocs.yml",
    "CHANGELOG.md",
    "docs/protocols.md",
    "docs/platform.md",
    "docs/hardware.md",
    "docs/remote-buses.md",
    "src/motorbus/__init__.py",
    "src/motorbus/py.typed",
    "tests/data/vectors.json",
    "tests/conftest.py",
    "tests/protocol/test_la.py",
    "tests/bus/test_timer_api.py",
    "examples/la_basics.py",
    "examples/project.toml",
    "benchmarks/run.py",
    "benchmarks/README.md",
)


@pytest.fixture(scope="module")
def unpacked(tmp_path_factory: pytest.TempPathFactory) -> Path:
    archive, _ = packaging.sdist(tmp_path_factory)
    return packaging.unpack(archive, tmp_path_factory.mktemp("sdist"))


def test_sdist_holds_tests_data_docs_examples_benchmarks(unpacked: Path) -> None:
    missing = [name for name in REQUIRED if not (unpacked / name).is_file()]
    assert not missing, f"not in the sdist: {missing}"
    # every tracked source and test module made it
    for folder in ("src/motorbus", "tests", "examples", "benchmarks"):
        here = {p.relative_to(packaging.ROOT) for p in (packaging.ROOT / folder).rglob("*.py")}
        there = {p.relative_to(unpacked) for p in (unpacked / folder).rglob("*.py")}
        assert here <= there, f"missing from the sdist: {sorted(map(str, here - there))}"
    assert not list(unpacked.rglob("__pycache__"))


def test_sdist_metadata_and_licence(
    unpacked: Path, tmp_path_factory: pytest.TempPathFactory
) -> None:
    _, log = packaging.sdist(tmp_path_factory)
    # setuptools warns about a licence table or licence classifiers: neither may appear
    noisy = [
        line
        for line in log.splitlines()
        if "deprecat" in line.lower()
        or (
            "licen" in line.lower()
            and not line.startswith(("adding license file 'LICENSE'", "copying LICENSE"))
        )
    ]
    assert not noisy, "\n".join(noisy)
    meta = email.parser.Parser().parsestr((unpacked / "PKG-INFO").read_text(encoding="utf-8"))
    assert meta["Name"] == "motorbus"
    assert meta["License-Expression"] == "MIT"
    assert meta.get_all("License-File") == ["LICENSE"]
    assert meta["Requires-Python"] == ">=3.11"
    classifiers = set(meta.get_all("Classifier") or [])
    assert {
        "Programming Language :: Python :: 3.11",
        "Programming Language :: Python :: 3.13",
        "Operating System :: POSIX :: Linux",
        "Framework :: AsyncIO",
        "Typing :: Typed",
        "Development Status :: 3 - Alpha",
    } <= classifiers
    assert not any(c.startswith("License ::") for c in classifiers)
    assert "Copyright (c) 2026 the motorbus authors" in (unpacked / "LICENSE").read_text()


# That the sdist's own tests pass from it unpacked, with its wheel installed in a fresh
# venv, is tests/test_interpreters.py's runs (on each supported interpreter found).
