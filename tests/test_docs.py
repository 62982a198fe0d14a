"""The documentation: the mkdocs site builds in strict mode, and every Python block runs.

``mkdocs build --strict`` fails on a broken link, a page left out of the navigation,
a docstring that names a parameter the signature does not have, or an API reference
(``::: motorbus.x``) that does not resolve.  The Python blocks of README.md and of
every page in docs/ are run as pasted, each in a fresh interpreter, against the
built-in simulators; a block may opt out only with a reason in the comment
``<!-- not run: REASON -->`` on the line before it.
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOC_FILES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
HAS_MKDOCS = all(
    importlib.util.find_spec(name) is not None for name in ("mkdocs", "mkdocstrings_handlers")
)
needs_mkdocs = pytest.mark.skipif(not HAS_MKDOCS, reason="pip install -e '.[docs]'")
NOT_RUN = re.compile(r"<!-- not run: (.+?) -->\s*$")


def mkdocs(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "mkdocs", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=300,
    )


@needs_mkdocs
@pytest.mark.timeout(300)
def test_the_site_builds_in_strict_mode_with_the_api_reference(tmp_path: Path) -> None:
    r = mkdocs("build", "--strict", "--site-dir", str(tmp_path / "site"))
    assert r.returncode == 0, r.stderr[-4000:]
    page = (tmp_path / "site" / "api" / "devices" / "index.html").read_text(encoding="utf-8")
    assert "motorbus.devices.la.InspireLA.move_to" in page  # rendered from the docstrings
    assert "ArrivalTimeoutError" in page


@needs_mkdocs
@pytest.mark.timeout(300)
def test_a_broken_api_reference_fails_the_strict_build(tmp_path: Path) -> None:
    docs = tmp_path / "docs"
    docs.mkdir()
    (docs / "index.md").write_text("# x\n\n::: motorbus.devices.la.NoSuchThing\n")
    (tmp_path / "mkdocs.yml").write_text(
        "site_name: x\nplugins:\n  - mkdocstrings:\n      handlers:\n        python:\n"
        f"          paths: [{ROOT / 'src'}]\n"
    )
    r = mkdocs("build", "--strict", "--site-dir", str(tmp_path / "site"), cwd=tmp_path)
    assert r.returncode != 0
    assert "NoSuchThing" in r.stderr


def python_blocks() -> list[tuple[str, str]]:
    """``(where, code)`` of every Python block in README.md and docs/, opt-outs left out."""
    found = []
    for path in DOC_FILES:
        lines = path.read_text(encoding="utf-8").splitlines()
        i = 0
        while i < len(lines):
            if lines[i].strip() == "```python":
                start = i
                i += 1
                body = []
                while lines[i].strip() != "```":
                    body.append(lines[i])
                    i += 1
                reason = NOT_RUN.search(lines[start - 1]) if start else None
                if reason is None:
                    where = f"{path.relative_to(ROOT)}:{start + 1}"
                    found.append((where, "\n".join(body) + "\n"))
            i += 1
    return found


BLOCKS = python_blocks()


def test_there_are_blocks_to_run_and_opt_outs_give_a_reason() -> None:
    assert len(BLOCKS) >= 10
    for path in DOC_FILES:
        text = path.read_text(encoding="utf-8")
        for comment in re.findall(r"<!-- not run:(.*?)-->", text):
            assert len(comment.strip()) > 10, f"{path.name}: say why a block is not run"


@pytest.mark.parametrize(("where", "code"), BLOCKS, ids=[w for w, _ in BLOCKS])
@pytest.mark.timeout(180)
def test_every_python_block_runs_as_pasted(where: str, code: str, tmp_path: Path) -> None:
    # Tests assert behaviour, not speed: a loaded CI machine gets a 50 ms host margin.
    env = {**os.environ, "MOTORBUS_HOST_MARGIN_MS": "50"}
    r = subprocess.run(
        [sys.executable, "-c", code],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=150,
    )
    assert r.returncode == 0, f"{where}:\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"


def test_architecture_says_why_each_dependency() -> None:
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    names = [re.split(r"[<>=\[; ]", d, maxsplit=1)[0] for d in project["dependencies"]]
    for extra in project["optional-dependencies"].values():
        names += [re.split(r"[<>=\[; ]", d, maxsplit=1)[0] for d in extra]
    text = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    deps = text[text.index("## Dependencies, and why these") :]
    missing = sorted({n for n in names if f"`{n}`" not in deps})
    assert not missing, f"docs/architecture.md does not say why {missing}"
