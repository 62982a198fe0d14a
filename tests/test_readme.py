"""README's set-up commands must stay true: CI runs exactly the test command."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def setup_commands() -> list[str]:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    first_block = re.search(r"```(?:sh|bash|console)?\n(.*?)```", text, re.S)
    assert first_block, "README must start with a code block holding the set-up commands"
    return [ln.strip() for ln in first_block.group(1).splitlines() if ln.strip() and ln[0] != "#"]


def test_readme_starts_with_demo_and_test_commands() -> None:
    commands = setup_commands()
    assert len(commands) == 2
    assert "motorbus demo" in commands[0]
    assert "pytest" in commands[1]


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
    assert {"ser2net", "socat", "linux-perf"} <= set(install[0].split())


def section(title: str) -> str:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    found = re.search(rf"^## {re.escape(title)}\n(.*?)(?=^## )", text, re.S | re.M)
    assert found, f"README has no '## {title}' section"
    return found.group(1)


def test_readme_has_an_install_section_for_users() -> None:
    install = section("Install")
    assert "pip install motorbus" in install
    assert "timerfd" in install and "Linux" in install  # what is Linux-only, and the fallback
    assert "call_at" in install


def test_readme_says_why_each_dependency() -> None:
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    names = [re.split(r"[<>=\[; ]", d, maxsplit=1)[0] for d in project["dependencies"]]
    for extra in project["optional-dependencies"].values():
        names += [re.split(r"[<>=\[; ]", d, maxsplit=1)[0] for d in extra]
    deps = section("Dependencies, and why these")
    missing = sorted({n for n in names if f"`{n}`" not in deps})
    assert not missing, f"README's Dependencies section does not explain {missing}"


def test_readme_links_the_guides_near_the_top() -> None:
    top = "\n".join((ROOT / "README.md").read_text(encoding="utf-8").splitlines()[:20])
    assert "docs/hardware.md" in top
