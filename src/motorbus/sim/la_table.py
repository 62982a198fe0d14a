"""The simulated LA actuator's control table: 256 bytes of RAM and a simulated flash.

One byte per possible index value (the index byte is 0..255, doc 002 C.5); every
register of ``motorbus.protocol.la.Register`` lives at its index, little-endian, and
the table header ``AA 55`` at index 0..1.  :class:`ControlTable` stores and reads
values; what a write *means* (an ID change, force zeroing, a new target that starts a
move) is decided by ``motorbus.sim.la.LAModel``, which owns a table.  Pure: no clock,
no I/O.
"""

from __future__ import annotations

from motorbus.protocol.la import Register

__all__ = ["ID_INDEX", "TABLE_BYTES", "TABLE_HEADER", "ControlTable"]

#: One RAM/flash byte per possible index value (the index byte is 0..255).
TABLE_BYTES = 256
#: Table header bytes (C.5 index 0..1), reserved: writes are ignored.
TABLE_HEADER = b"\xaa\x55"

#: Where the 1-byte ID lives in the control table (3.6 index 2): read on every frame.
ID_INDEX = Register.ID.index
#: (index, size, signed) of every register, looked up once: Enum attribute access is
#: slow and the model reads registers on every frame.
_LAYOUT = {reg: (reg.index, reg.size, reg.signed) for reg in Register}
#: Bytes a table write leaves alone: the header and every read-only register.
_PROTECTED = frozenset(
    {0, 1}
    | {at for reg in Register if not reg.writable for at in range(reg.index, reg.index + reg.size)}
)


class ControlTable:
    """The control table in RAM (what reads and writes see) and in flash.

    Args:
        id: the actuator ID written into the factory table.
        baud_code: the ``BaudCode`` written into it.
        target: the initial target register value.

    Every register starts at its factory default (``Register``'s ``default``).
    """

    __slots__ = ("flash", "ram")

    def __init__(self, *, id: int, baud_code: int, target: int) -> None:
        #: The table as reads and writes see it; ``ram[index]`` is one byte.
        self.ram = bytearray(TABLE_BYTES)
        self.ram[0:2] = TABLE_HEADER
        for reg in Register:
            if reg.value.default is not None:
                self.put(reg, reg.value.default)
        self.put(Register.ID, id)
        self.put(Register.BAUD, baud_code)
        self.put(Register.TARGET, target)
        #: What ``SAVE`` stored and a power cycle reloads.
        self.flash = bytearray(self.ram)

    @property
    def id(self) -> int:
        """The ID in RAM (index 2)."""
        return self.ram[ID_INDEX]

    def get(self, reg: Register) -> int:
        """The value of ``reg`` in RAM."""
        index, size, signed = _LAYOUT[reg]
        return int.from_bytes(self.ram[index : index + size], "little", signed=signed)

    def put(self, reg: Register, value: int) -> None:
        """Store ``value`` in ``reg``, unchecked but for its size.

        Raises:
            LocalProtocolError: ``value`` does not fit the register's size.
        """
        self.ram[reg.index : reg.index + reg.size] = reg.encode_value(value)

    def raw(self, reg: Register) -> bytes:
        """The bytes of ``reg`` in RAM."""
        return bytes(self.ram[reg.index : reg.index + reg.size])

    def set_raw(self, reg: Register, raw: bytes) -> None:
        """Put back bytes ``raw(reg)`` returned."""
        self.ram[reg.index : reg.index + reg.size] = raw

    def read(self, index: int, count: int) -> bytes:
        """``count`` RAM bytes from ``index`` (as a table read returns them)."""
        return bytes(self.ram[index : index + count])

    def write(self, index: int, data: bytes) -> None:
        """Write ``data`` at ``index``, leaving the header and read-only registers alone."""
        for offset, byte in enumerate(data):
            at = index + offset
            if at not in _PROTECTED:
                self.ram[at] = byte

    def save(self) -> None:
        """``SAVE``: copy RAM to flash."""
        self.flash[:] = self.ram

    def reload(self) -> None:
        """Power-up: RAM reloads from flash."""
        self.ram[:] = self.flash
