"""Public names loaded from their modules on first use (PEP 562 ``__getattr__``).

A package whose ``__init__`` would otherwise import everything it exports lists its
names by module in one ``_EXPORTS`` table and asks :func:`lazy_names` for its
``__all__``, ``__getattr__`` and ``__dir__``; type checkers read the package's
``TYPE_CHECKING`` imports of the same names (tests/test_public_api.py checks that the
two agree).  ``motorbus``, ``motorbus.blocking``, ``motorbus.rig`` and
``motorbus.protocol.project_stepper`` do this.  It lives in the protocol layer, the
lowest any of them may import, and imports nothing of motorbus.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Iterable, Mapping
from typing import Any

__all__ = ["lazy_names"]


def lazy_names(
    package: str, exports: Mapping[str, Iterable[str]], *, also: Iterable[str] = ()
) -> tuple[list[str], Callable[[str], Any], Callable[[], list[str]]]:
    """``(__all__, __getattr__, __dir__)`` for ``package``, whose names ``exports`` maps
    by the module each is loaded from; ``also``: names the package defines itself, for
    ``__all__``.  A name is loaded once, then kept in the package's namespace."""
    where = {name: module for module, names in exports.items() for name in names}
    namespace = vars(sys.modules[package])

    def __getattr__(name: str) -> Any:
        module = where.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        namespace[name] = value
        return value

    names = sorted([*where, *also])

    def __dir__() -> list[str]:
        return sorted({*namespace, *names})

    return names, __getattr__, __dir__
