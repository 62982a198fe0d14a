"""The LA control table (doc 002 section 3.6): one ``Register`` per field."""

from __future__ import annotations

import enum
from dataclasses import dataclass

from motorbus.errors import LocalProtocolError, RemoteProtocolError
from motorbus.protocol.base import check_int
from motorbus.protocol.la.wire import (
    ID_MAX,
    ID_MIN,
    POSITION_MAX,
    POSITION_MIN,
    REPORTED_POSITION_MAX,
    REPORTED_POSITION_MIN,
    TARGET_INDEX,
    BaudCode,
)

# --- the control table ------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class RegisterInfo:
    """The layout of one documented control-table register (doc 002 section 3.6, C.5).

    ``minimum``/``maximum`` are the write range for writable registers and the nominal
    range of the reading for read-only ones.  ``default`` is the factory value, if any.
    """

    index: int
    size: int
    signed: bool
    minimum: int
    maximum: int
    writable: bool
    unit: str
    default: int | None


class Register(enum.Enum):
    """Every documented register of the LA control table (doc 002 section 3.6, C.5).

    Look up by name with ``Register["TARGET"]`` or ``Register.by_name("target")``, by index
    with ``Register.by_index(55)``.
    """

    _value_: RegisterInfo

    #: Actuator ID; takes effect at once, save to keep (3.6 index 2; A2-12).
    ID = RegisterInfo(2, 1, False, ID_MIN, ID_MAX, True, "", 1)
    #: Baud code (``BaudCode``); needs save and a power cycle (3.6 index 12; A2-13).
    BAUD = RegisterInfo(12, 1, False, 0, 3, True, "code", BaudCode.B921600)
    #: Current position, int16, -20..2020 (3.6 index 26).
    POSITION = RegisterInfo(
        26, 2, True, REPORTED_POSITION_MIN, REPORTED_POSITION_MAX, False, "", None
    )
    #: Force-sensor zero: write 1 to take the present reading as zero (3.6 index 31).
    FORCE_ZERO = RegisterInfo(31, 1, False, 1, 1, True, "", 0)
    #: Over-current limit, 300..1500 mA (3.6 index 32).
    OVER_CURRENT_LIMIT = RegisterInfo(32, 2, False, 300, 1500, True, "mA", 1500)
    #: Target position 0..2000; writing it also starts a move (3.6 index 55; A2-21).
    TARGET = RegisterInfo(TARGET_INDEX, 2, False, POSITION_MIN, POSITION_MAX, True, "", None)
    #: Force in grams, int16 (3.6 index 76; A2-07).
    FORCE = RegisterInfo(76, 2, True, -32768, 32767, False, "g", None)
    #: Raw force ADC, 12-bit so nominally 0..4095 (3.6 index 78; A2-07).
    RAW_FORCE = RegisterInfo(78, 2, False, 0, 4095, False, "counts", None)
    #: Over-temperature limit in 0.1 degC, [(recovery + 5) * 10, 800] (3.6 index 98; A2-14).
    OVER_TEMPERATURE_LIMIT = RegisterInfo(98, 2, False, 250, 800, True, "0.1 degC", 800)
    #: Recovery temperature in 0.1 degC, [200, (over-temp - 5) * 10] (3.6 index 100; A2-14).
    RECOVERY_TEMPERATURE = RegisterInfo(100, 2, False, 200, 750, True, "0.1 degC", 600)

    def __repr__(self) -> str:
        return f"Register.{self.name}"

    @property
    def index(self) -> int:
        """First control-table byte of the register."""
        return self.value.index

    @property
    def size(self) -> int:
        """Size in bytes (1 or 2)."""
        return self.value.size

    @property
    def signed(self) -> bool:
        """True if the register holds a two's-complement value."""
        return self.value.signed

    @property
    def minimum(self) -> int:
        """Lowest allowed write value (read-only registers: lowest nominal reading)."""
        return self.value.minimum

    @property
    def maximum(self) -> int:
        """Highest allowed write value (read-only registers: highest nominal reading)."""
        return self.value.maximum

    @property
    def writable(self) -> bool:
        """True if the host may write the register."""
        return self.value.writable

    @property
    def field_name(self) -> str:
        """The name used in error messages, e.g. ``over_current_limit``."""
        return self.name.lower()

    @classmethod
    def by_name(cls, name: str) -> Register:
        """Return the register called ``name`` (case-insensitive).

        Raises:
            LocalProtocolError: no register has that name.
        """
        try:
            return cls[name.upper()]
        except KeyError:
            names = ", ".join(r.name for r in cls)
            raise LocalProtocolError(
                f"register={name!r} is not allowed: choose one of {names}",
                field="register",
                value=name,
            ) from None

    @classmethod
    def by_index(cls, index: int) -> Register:
        """Return the register that starts at control-table ``index``.

        Raises:
            LocalProtocolError: no documented register starts there.
        """
        for reg in cls:
            if reg.index == index:
                return reg
        indices = ", ".join(str(r.index) for r in cls)
        raise LocalProtocolError(
            f"index={index!r} is not allowed: registers start at {indices}",
            field="index",
            value=index,
        )

    @classmethod
    def at(cls, index: int, size: int) -> Register | None:
        """Return the register exactly covering ``size`` bytes at ``index``, else ``None``."""
        for reg in cls:
            if reg.index == index and reg.size == size:
                return reg
        return None

    def check_value(self, value: object) -> int:
        """Return ``value`` if it may be written to this register.

        Raises:
            LocalProtocolError: the register is read-only, or the value is out of range.
        """
        if not self.writable:
            raise LocalProtocolError(
                f"register {self.name} (index {self.index}) is read-only",
                field="register",
                value=self,
            )
        return check_int(self.field_name, value, self.minimum, self.maximum)

    def encode_value(self, value: int) -> bytes:
        """Return the little-endian bytes of ``value`` in this register's size and sign.

        Raises:
            LocalProtocolError: ``value`` does not fit the register's size and sign.
        """
        bits = 8 * self.size
        lo, hi = (
            (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if self.signed else (0, (1 << bits) - 1)
        )
        check_int(self.field_name, value, lo, hi)
        return value.to_bytes(self.size, "little", signed=self.signed)

    def decode_value(self, data: bytes) -> int:
        """Decode the register's little-endian bytes (``len(data)`` must equal ``size``).

        Raises:
            RemoteProtocolError: wrong number of bytes.
        """
        if len(data) != self.size:
            raise RemoteProtocolError(
                f"register {self.name} needs {self.size} bytes, got {len(data)}", raw=bytes(data)
            )
        return int.from_bytes(data, "little", signed=self.signed)
