"""No test waits without a bound: a ``while ...: await asyncio.sleep(...)`` loop that
never ends hangs the run until pytest-timeout; ``tests.waiting.eventually`` fails with
a message instead.  And no property test has a time limit: tests assert behaviour."""

from __future__ import annotations

import ast
import re
from pathlib import Path

from hypothesis import HealthCheck, settings

TESTS = Path(__file__).resolve().parent


def _is_timeout_block(node: ast.AST) -> bool:
    """``async with asyncio.timeout(...)`` (or ``timeout(...)``): a bounded block."""
    return isinstance(node, ast.AsyncWith) and any(
        isinstance(item.context_expr, ast.Call)
        and ast.unparse(item.context_expr.func).split(".")[-1] in ("timeout", "timeout_at")
        for item in node.items
    )


def _bare_sleep_loops(tree: ast.AST) -> list[int]:
    lines: list[int] = []
    _visit(tree, bounded=False, lines=lines)
    return lines


def _visit(node: ast.AST, *, bounded: bool, lines: list[int]) -> None:
    bounded = bounded or _is_timeout_block(node)
    for child in ast.iter_child_nodes(node):
        _visit(child, bounded=bounded, lines=lines)
    if not bounded:
        _check(node, lines)


def _check(node: ast.AST, lines: list[int]) -> None:
    if isinstance(node, ast.While) and len(node.body) == 1:
        stmt = node.body[0]
        if (
            isinstance(stmt, ast.Expr)
            and isinstance(stmt.value, ast.Await)
            and isinstance(stmt.value.value, ast.Call)
            and ast.unparse(stmt.value.value.func) == "asyncio.sleep"
        ):
            lines.append(node.lineno)


def test_no_unbounded_sleep_loops() -> None:
    found = [
        f"{path.relative_to(TESTS)}:{line}"
        for path in sorted(TESTS.rglob("*.py"))
        if path.name != "waiting.py"
        for line in _bare_sleep_loops(ast.parse(path.read_text(encoding="utf-8")))
    ]
    assert found == [], "use tests.waiting.eventually: " + ", ".join(found)


def test_property_tests_have_no_time_limit() -> None:
    """Hypothesis's deadline per example and its "generation too slow" health check are
    timing assertions, which a loaded shared machine fails (one did: an example took
    1.1 s to generate).  The suite's profile (tests/conftest.py) turns both off, and no
    test turns a deadline back on."""
    assert settings.default.deadline is None
    assert HealthCheck.too_slow in settings.default.suppress_health_check
    with_deadline = re.compile(r"@settings\([^)]*deadline\s*=")
    offenders = [
        path.relative_to(TESTS).as_posix()
        for path in TESTS.rglob("*.py")
        if with_deadline.search(path.read_text(encoding="utf-8"))
    ]
    assert offenders == []
