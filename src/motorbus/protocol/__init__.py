"""The sans-I/O protocol layer: bytes in, typed frames and events out.

Nothing in this package imports asyncio, reads a clock or touches a port.
"""
