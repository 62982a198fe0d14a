"""The dashboard's page served as ``motorbus dashboard`` serves it (``serve_page``: one
listening socket, the viewers on their own loop), and a client of it with relative
paths, for the tests."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Any

import aiohttp
from aiohttp import web

from motorbus.dashboard.server import serve_page


@dataclass
class PageClient:
    """``get``/``post``/``request``/``ws_connect`` with paths such as ``/api/state``."""

    session: aiohttp.ClientSession
    host: str
    port: int

    def get(self, path: str, **kw: Any) -> Any:
        return self.session.get(path, **kw)

    def post(self, path: str, **kw: Any) -> Any:
        return self.session.post(path, **kw)

    def request(self, method: str, path: str, **kw: Any) -> Any:
        return self.session.request(method, path, **kw)

    def ws_connect(self, path: str, **kw: Any) -> Any:
        return self.session.ws_connect(path, **kw)


@asynccontextmanager
async def page_client(app: web.Application) -> AsyncIterator[PageClient]:
    """Serve ``app`` on a free loopback port; a client of it."""
    async with serve_page(app, "127.0.0.1", 0) as server:
        base = f"http://127.0.0.1:{server.port}"
        async with aiohttp.ClientSession(base_url=base) as session:
            yield PageClient(session, "127.0.0.1", server.port)
