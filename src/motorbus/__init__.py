"""motorbus: asyncio buses of serial motion devices."""
