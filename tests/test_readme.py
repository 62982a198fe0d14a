"""README's commands work; what they say is checked by running them, not by phrases.

The set-up commands must stay exactly what CI runs; the tour's shell block is run as
pasted against a simulator; every relative link resolves; every extra named exists.
README's Python blocks are run by tests/test_docs.py with those of docs/.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text(encoding="utf-8")


def setup_commands() -> list[str]:
    first_block = re.search(r"```(?:sh|bash|console)?\n(.*?)```", README, re.S)
    assert first_block, "README must start with a code block holding the set-up commands"
    return [ln.strip() for ln in first_block.group(1).splitlines() if ln.strip() and ln[0] != "#"]


def test_readme_starts_with_demo_and_test_commands() -> None:
    commands = setup_commands()
    assert len(commands) == 2
    assert commands[0].endswith("&& motorbus demo")
    assert commands[1].endswith("&& python -m pytest -q -p no:cacheprovider -n auto")


def test_ci_runs_exactly_the_readme_test_command() -> None:
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert setup_commands()[1] in ci.splitlines()


def test_setup_commands_make_a_venv_first() -> None:
    """PEP 668 systems refuse a bare ``pip install``; both lines must work on them."""
    for command in setup_commands():
        assert command.startswith("python3 -m venv .venv && . .venv/bin/activate && pip install")


def test_ci_installs_the_debian_packages_the_tests_and_benchmarks_use() -> None:
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    install = [ln for ln in ci.splitlines() if "apt-get install" in ln]
    assert install, ".ci/run installs no Debian package"
    assert {"ser2net", "socat", "linux-perf", "valgrind"} <= set(install[0].split())


def pyproject() -> dict[str, object]:
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]


def test_every_extra_the_readme_installs_exists() -> None:
    extras = set(pyproject()["optional-dependencies"])  # type: ignore[call-overload]
    named = set(re.findall(r"(?:motorbus|\.)\[([a-z-]+)\]", README))
    named |= set(re.findall(r"`([a-z-]+)` \(", README)) & extras  # "Other extras: `x` (...)"
    assert named, "README installs no extra"
    assert named <= extras, f"README names extras that pyproject.toml lacks: {named - extras}"


def test_every_relative_link_resolves() -> None:
    links = re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", README)
    relative = [link for link in links if "://" not in link]
    assert relative, "README links no guide"
    missing = [link for link in relative if not (ROOT / link).exists()]
    assert not missing, f"README links to files that do not exist: {missing}"


def test_the_project_urls_point_at_the_changelog_and_the_docs() -> None:
    urls = pyproject()["urls"]
    assert isinstance(urls, dict)
    assert {"Homepage", "Documentation", "Issues", "Changelog"} <= set(urls)
    assert urls["Changelog"].endswith("/CHANGELOG.md") and (ROOT / "CHANGELOG.md").is_file()


def tour_block() -> str:
    blocks = re.findall(r"```sh\n(.*?)```", README, re.S)
    tour = [b for b in blocks if "motorbus sim" in b]
    assert len(tour) == 1, "README's tour has one shell block that starts a simulator"
    return tour[0]


@pytest.mark.timeout(180)
def test_the_tour_commands_run_as_pasted(tmp_path: Path) -> None:
    env = {
        **os.environ,
        "MOTORBUS_HOST_MARGIN_MS": "50",  # behaviour, not speed, on a loaded machine
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
    }
    r = subprocess.run(
        ["bash", "-e", "-c", tour_block()],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=150,
    )
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-3000:]
    lines = r.stdout.splitlines()
    assert "1,2,3" in lines  # the scan found the three simulated actuators
    assert any(line.split()[:2] == ["2", "1500"] for line in lines)  # la:2's new target
    assert any("MoveTo id=1 position=1300" in line for line in lines)  # decode
