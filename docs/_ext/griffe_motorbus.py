"""A griffe extension for the API reference (mkdocs.yml loads it for mkdocstrings).

It changes what the reference shows, never the code: the docstrings and the object
tree it edits are the copies griffe loaded for the site.

* reST roles (``:class:`Streamer```, ``:meth:`~Bus.close```, ``:func:``, ``:attr:``,
  ``:mod:``, ``:data:``, ``:exc:``, ``:obj:``, ``:const:``, also with ``py:``) become
  cross-references, resolved the way Python resolves the name where the docstring is:
  the object itself, then the class, module and packages around it, imports included.
  A target the site renders becomes a link; one it does not render (a private helper,
  an object without a docstring, another library) stays plain code.  A name that
  resolves nowhere is a warning, which fails the strict build.
* A name a module imports and re-exports (``motorbus.sim.SimProcess``) is documented
  once, on the page of the module that defines it, when a page renders that module;
  the re-export is left out (it stays in the reference when it is the only place).
* The objects listed in ``internal`` are left out: methods public by name that only the
  package itself calls (``Stream.end``, ``Stream.next_targets``, ...).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import griffe

_log = griffe.get_logger("griffe_motorbus")

#: ``:role:`target```, ``:role:`~target```, ``:role:`title <target>```.
ROLE = re.compile(
    r":(?:py:)?(?P<role>class|func|meth|attr|mod|data|exc|obj|const):"
    r"`(?P<text>[^`]+)`"
)
#: The ``::: identifier`` lines of the pages: the modules the site renders.
DIRECTIVE = re.compile(r"^:::\s+(?P<id>[\w.]+)\s*$", re.MULTILINE)


class MotorbusReference(griffe.Extension):
    """Roles to cross-references, each public name once, internals left out."""

    def __init__(self, pages: str = "docs", internal: list[str] | None = None) -> None:
        super().__init__()
        self.pages = Path(pages)
        self.internal = list(internal or [])

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **_: Any) -> None:
        if pkg.name != "motorbus":
            return
        rendered = self._rendered_modules()
        everything = _walk(pkg)
        for obj in everything:
            if not obj.is_alias and obj.docstring is not None:
                obj.docstring.value = ROLE.sub(
                    lambda m, o=obj: _reference(pkg, o, m), obj.docstring.value
                )
        for obj in everything:
            if obj.is_alias:
                self._hide_reexport(obj, rendered)
            elif obj.name.startswith("__") and obj.name.endswith("__") and obj.is_function:
                _leave_out(obj)  # ``__repr__`` and co. (``__init__`` is merged into the class)
        for path in self.internal:
            obj = _lookup(pkg, path)
            if obj is None or obj.is_alias:
                _log.warning("griffe_motorbus: internal %s names no object defined there", path)
            else:
                _leave_out(obj)

    def _rendered_modules(self) -> set[str]:
        found: set[str] = set()
        for page in sorted(self.pages.rglob("*.md")):
            found.update(m["id"] for m in DIRECTIVE.finditer(page.read_text(encoding="utf-8")))
        return found

    @staticmethod
    def _hide_reexport(alias: griffe.Object | griffe.Alias, rendered: set[str]) -> None:
        parent = alias.parent
        if parent is None or not parent.is_module:
            return
        try:
            target = alias.final_target
        except griffe.AliasResolutionError:
            return  # another library's name: not documented here in any case
        home = target.parent
        if home is not None and home.path in rendered and home.path != parent.path:
            alias.public = False


def _leave_out(obj: griffe.Object | griffe.Alias) -> None:
    """Take ``obj`` out of the tree the site is rendered from (also from every alias of
    its class: ``public = False`` would hide it only where it is defined)."""
    if obj.parent is not None and obj.name != "__init__":
        del obj.parent.members[obj.name]


def _walk(obj: griffe.Object | griffe.Alias) -> list[griffe.Object | griffe.Alias]:
    """``obj`` and everything it defines (aliases are yielded, not entered)."""
    out = [obj]
    if obj.is_alias:
        return out
    for member in obj.members.values():
        out.extend(_walk(member))
    return out


def _lookup(pkg: griffe.Module, path: str) -> griffe.Object | griffe.Alias | None:
    if path == pkg.path:
        return pkg
    if not path.startswith(pkg.path + "."):
        return None
    try:
        return pkg[path[len(pkg.path) + 1 :]]
    except (KeyError, griffe.AliasResolutionError):
        return None


def _member(scope: griffe.Object | griffe.Alias, dotted: str) -> Any:
    """``scope.a.b`` (inherited members included), or None."""
    obj: Any = scope
    for part in dotted.split("."):
        try:
            if obj.is_alias:
                obj = obj.final_target
            members = obj.all_members if obj.is_class else obj.members
        except griffe.AliasResolutionError:
            return None
        if part not in members:
            return None
        obj = members[part]
    return obj


def _resolve(pkg: griffe.Module, owner: griffe.Object, name: str) -> str | None:
    """The canonical path of what ``name`` means in ``owner``'s docstring, or None.

    An external name (``asyncio.Task``) comes back as the path it was imported as.
    """
    found = _lookup(pkg, name)
    scope: Any = owner
    while found is None and scope is not None:
        found = _member(scope, name)
        scope = scope.parent
    if found is None:
        return None
    try:
        return str(found.final_target.path if found.is_alias else found.path)
    except griffe.AliasResolutionError:
        return str(found.target_path)


def _reference(pkg: griffe.Module, owner: griffe.Object, match: re.Match[str]) -> str:
    text = match["text"].strip()
    titled = re.fullmatch(r"(?P<title>.+?)\s*<(?P<target>[^<>]+)>", text)
    if titled:
        title, target = titled["title"], titled["target"]
    else:
        target = text.lstrip("!")
        title = target.lstrip("~.").rsplit(".", 1)[-1] if "~" in target else target
    target = target.lstrip("~!.")
    code = f"<code>{title}</code>"
    path = _resolve(pkg, owner, target)
    if path is None:
        where = f"{owner.relative_filepath}:{owner.lineno}"
        _log.warning("%s: %s in the docstring of %s names nothing", where, match[0], owner.path)
        return code
    if not path.startswith(pkg.path + ".") and path != pkg.path:
        return code  # another library: the site has no page for it
    # ``optional``: linked when the site renders the target, plain code when it does not.
    return f'<autoref identifier="{path}" optional>{code}</autoref>'
