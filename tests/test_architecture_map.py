"""docs/architecture.md is a true map: its module tree names every module of motorbus,
and every module path the page names exists.

The tree is the page's first code block.  An entry is a line whose first word, at the
tree's two-space steps, is a module (``name.py``) or a package (``name/``); the words
after it, and the continuation lines indented past it, describe it.  A ``name.py`` in a
description is a module of the package described (of the entry's own package for a
module entry): ``bus/  bus.py (Bus), engine.py`` names ``bus/bus.py`` and
``bus/engine.py``; a path with a slash in it is taken from ``src/motorbus``.  Every
``.py`` file under ``src/motorbus`` but the ``__init__.py`` files must be named so.

Anywhere on the page, a path ending in ``.py`` (in or out of the tree) and a dotted
``motorbus.`` name must name something that exists: ``tests/...`` and ``benchmarks/...``
paths from the repository, other paths from ``src/motorbus``, a bare file name somewhere
under it, a dotted name as a module and then names its module defines or imports.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "motorbus"
DOC = ROOT / "docs" / "architecture.md"

#: The first word of a tree line: a module or a package.
ENTRY = re.compile(r"^( *)([A-Za-z_]\w*(?:\.py|/))(?:\s|$)")
#: A module path (``engine.py``, ``bus/engine.py``, ``tests/test_docs.py``).
PY_PATH = re.compile(r"(?<![\w./<>-])((?:[A-Za-z_][\w-]*/)*[A-Za-z_]\w*\.py)\b")
#: A dotted name under motorbus (``motorbus.bus.stats``, ``motorbus.connect``).
DOTTED = re.compile(r"\bmotorbus(?:\.[A-Za-z_]\w*)+")
#: A repository path that is not a module of the package.
REPO_DIRS = ("tests/", "benchmarks/", "docs/", "examples/", "src/")


def files(src: Path) -> set[str]:
    """Every ``.py`` file of the package at ``src``, as a path relative to it."""
    return {path.relative_to(src).as_posix() for path in src.rglob("*.py")}


def modules(src: Path) -> set[str]:
    """The modules the tree must name: every file but the ``__init__.py`` files."""
    return {path for path in files(src) if not path.endswith("__init__.py")}


def tree_block(text: str) -> list[str]:
    """The lines of the page's first code block (the module tree)."""
    match = re.search(r"^```[^\n]*\n(.*?)^```", text, re.S | re.M)
    assert match, "the page has no code block (the module tree)"
    return match.group(1).splitlines()


def tree_modules(lines: list[str]) -> tuple[set[str], list[str]]:
    """The module paths the tree names, and what it names wrongly."""
    named: set[str] = set()
    bad: list[str] = []
    stack: list[tuple[int, str]] = []  # (indent, package path) of the open packages
    current: tuple[int, str] | None = None  # the entry being described: indent, package
    top = None
    for line in lines:
        if not line.strip():
            continue
        if top is None:  # the root line, src/motorbus/
            top = len(line) - len(line.lstrip())
            continue
        entry = ENTRY.match(line)
        indent = len(entry.group(1)) if entry else -1
        limit = current[0] + 2 if current is not None else top + 2
        if entry and indent <= limit and (indent - top) % 2 == 0 and indent > top:
            while stack and stack[-1][0] >= indent:
                stack.pop()
            parent = stack[-1][1] if stack else ""
            name = entry.group(2)
            if name.endswith("/"):
                package = parent + name
                stack.append((indent, package))
                current = (indent, package)
            else:
                named.add(parent + name)
                current = (indent, parent)
            words = line[entry.end() :]
        elif current is not None:
            words = line
        else:
            bad.append(f"a tree line outside any entry: {line.strip()!r}")
            continue
        for path in PY_PATH.findall(words):
            named.add(path if "/" in path else current[1] + path)
    return named, bad


def missing_paths(text: str, src: Path, repo: Path) -> list[str]:
    """Every ``.py`` path and dotted ``motorbus.`` name of the page that does not exist."""
    names = {path.name for path in src.rglob("*.py")}
    bad: list[str] = []
    for path in sorted(set(PY_PATH.findall(text))):
        if path.startswith(REPO_DIRS):
            ok = (repo / path).is_file()
        elif "/" in path:
            ok = (src / path.removeprefix("motorbus/")).is_file()
        else:
            ok = path in names
        if not ok:
            bad.append(path)
    for dotted in sorted(set(DOTTED.findall(text))):
        if not _resolves(dotted.split(".")[1:], src):
            bad.append(dotted)
    return bad


def _resolves(bits: list[str], src: Path) -> bool:
    """``bits`` name a module under ``src``, then names that module binds."""
    here = src
    for i, bit in enumerate(bits):
        if (here / bit / "__init__.py").is_file():
            here = here / bit
            continue
        if (here / f"{bit}.py").is_file():
            return _binds(here / f"{bit}.py", bits[i + 1 : i + 2])
        return _binds(here / "__init__.py", [bit])
    return True


def _binds(path: Path, names: list[str]) -> bool:
    """The module at ``path`` defines, imports or assigns each of ``names`` (or lists
    it among the names it loads on first use)."""
    if not names:
        return True
    text = path.read_text(encoding="utf-8")
    return all(re.search(rf"\b{re.escape(name)}\b", text) for name in names)


def problems(text: str, src: Path, repo: Path) -> list[str]:
    named, bad = tree_modules(tree_block(text))
    out = list(bad)
    out += [f"not in the module tree: {m}" for m in sorted(modules(src) - named)]
    out += [f"named in the tree, not a module: {m}" for m in sorted(named - files(src))]
    out += [f"named, does not exist: {p}" for p in missing_paths(text, src, repo)]
    return out


def test_the_architecture_page_names_every_module_and_only_real_ones() -> None:
    assert problems(DOC.read_text(encoding="utf-8"), SRC, ROOT) == []


def test_the_map_check_fails_on_a_module_left_out_or_made_up(tmp_path: Path) -> None:
    # A package of its own, so that the check is seen to fail (nothing is added to src).
    src = tmp_path / "src" / "motorbus"
    (src / "bus").mkdir(parents=True)
    (src / "protocol" / "la").mkdir(parents=True)
    for name in (
        "__init__.py",
        "errors.py",
        "bus/__init__.py",
        "bus/bus.py",
        "bus/core.py",
        "protocol/__init__.py",
        "protocol/base.py",
        "protocol/la/__init__.py",
        "protocol/la/wire.py",
    ):
        (src / name).write_text("Bus = 1\n", encoding="utf-8")
    page = (
        "# Map\n\n"
        "```\n"
        "src/motorbus/\n"
        "  errors.py        every exception\n"
        "  protocol/        sans-I/O:\n"
        "    base.py          Command; see also\n"
        "                     protocol/la/wire.py\n"
        "    la/              wire.py\n"
        "  bus/             bus.py (Bus), core.py (the\n"
        "                   pure core)\n"
        "```\n\n"
        "Requests go through `bus/bus.py` (`motorbus.bus.bus.Bus`).\n"
    )
    assert problems(page, src, tmp_path) == []
    # A module added without a line in the tree:
    (src / "bus" / "engine.py").write_text("", encoding="utf-8")
    assert problems(page, src, tmp_path) == ["not in the module tree: bus/engine.py"]
    page = page.replace("core.py (the", "core.py, engine.py (the")
    assert problems(page, src, tmp_path) == []
    # A module the tree or the text names that does not exist:
    assert problems(page.replace("wire.py\n  bus/", "wires.py\n  bus/"), src, tmp_path) == [
        "named in the tree, not a module: protocol/la/wires.py",
        "named, does not exist: wires.py",
    ]
    assert problems(page + "And `bus/timer.py`.\n", src, tmp_path) == [
        "named, does not exist: bus/timer.py"
    ]
    assert problems(page + "And `motorbus.bus.timer`.\n", src, tmp_path) == [
        "named, does not exist: motorbus.bus.timer"
    ]
