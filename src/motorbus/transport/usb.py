"""Serial ports named by what does not change: a USB adapter's IDs and serial number.

Linux numbers USB serial adapters in the order it finds them: the adapter that was
``/dev/ttyUSB0`` comes back as ``/dev/ttyUSB1`` after an unplug while the old name was
still held open, or after a reboot with another adapter found first.  A bus may
therefore name its adapter by what does not change::

    usb:serial=A12345          the adapter with this USB serial number
    usb:0403:6001              the one adapter with this vendor and product ID (hex)
    usb:0403:6001:A12345       both
    /dev/serial/by-id/usb-FTDI_FT232R_USB_UART_A12345-if00-port0   (udev's link)

A ``usb:`` URL is checked when it is given (:func:`parse_usb_url`: bus file load,
:class:`~motorbus.transport.SerialTransport` construction) and resolved to a device
path each time the port is opened (:func:`resolve_port`): at the first open and at
every reconnect, so an adapter that comes back under another name is found again.  A
device path is resolved through its symlinks at the same moments.

Everything here is read from sysfs: ``/sys/class/tty/NAME/device`` leads to the USB
interface, whose parent USB device holds ``idVendor``, ``idProduct``, ``serial``,
``manufacturer`` and ``product``; ``device/driver`` names the driver; the usb-serial
drivers that have one (FTDI) publish the receive latency timer in
``/sys/bus/usb-serial/devices/NAME/latency_timer``.  Plain functions, no asyncio;
the roots (:data:`SYSFS`, :data:`DEV`) are module values a test points at a fake tree,
or arguments.
"""

from __future__ import annotations

import errno
import os
import re
from dataclasses import dataclass
from typing import Any

from motorbus.errors import LocalProtocolError

__all__ = [
    "DEV",
    "SYSFS",
    "URL_FORMS",
    "USB_SCHEME",
    "USB_SERIAL_SYSFS",
    "SerialPortInfo",
    "UsbSelector",
    "is_usb_url",
    "list_serial_ports",
    "parse_usb_url",
    "port_identity",
    "port_info",
    "read_latency_timer_ms",
    "resolve_port",
]

#: The scheme of a port named by its USB identity.
USB_SCHEME = "usb:"
#: The forms a ``usb:`` URL may take (error messages and docs quote them).
URL_FORMS = ("usb:serial=SERIAL", "usb:VID:PID", "usb:VID:PID:SERIAL")
#: Where sysfs is mounted; a test points it at a fake tree.
SYSFS = "/sys"
#: Where the device nodes and udev's ``serial/by-id`` links are.
DEV = "/dev"
#: Where the Linux usb-serial drivers publish an adapter's receive latency timer (ms).
USB_SERIAL_SYSFS = "/sys/bus/usb-serial/devices"
#: ``USB_SERIAL_SYSFS`` below a sysfs root.
_USB_SERIAL_DEVICES = os.path.join("bus", "usb-serial", "devices")
_HEX4 = re.compile(r"[0-9A-Fa-f]{4}")
#: A serial number: printable, no blank (sysfs strips the string; udev's link replaces
#: blanks, so one with a blank could not be told apart reliably).
_SERIAL = re.compile(r"[!-~]+")
_FORMS_TEXT = (
    f"allowed forms: {', '.join(URL_FORMS)} (VID and PID: 4 hex digits, e.g. usb:0403:6001)"
)


def is_usb_url(url: str) -> bool:
    """True if ``url`` names a port by its USB identity (``usb:...``)."""
    return url.startswith(USB_SCHEME)


@dataclass(frozen=True, slots=True)
class UsbSelector:
    """Which USB adapter a ``usb:`` URL names; an empty field matches any value.

    Attributes:
        vid: vendor ID, 4 lower-case hex digits as sysfs writes it, or ``""``.
        pid: product ID, likewise, or ``""``.
        serial: the USB serial number (exact, case-sensitive), or ``""``.
    """

    vid: str = ""
    pid: str = ""
    serial: str = ""

    def matches(self, port: SerialPortInfo) -> bool:
        """True if ``port`` is this adapter."""
        return (
            port.is_usb
            and (not self.vid or port.vid == self.vid)
            and (not self.pid or port.pid == self.pid)
            and (not self.serial or port.serial == self.serial)
        )

    def __str__(self) -> str:
        if not self.vid:
            return f"{USB_SCHEME}serial={self.serial}"
        tail = f":{self.serial}" if self.serial else ""
        return f"{USB_SCHEME}{self.vid}:{self.pid}{tail}"


def _bad(url: str, why: str, field: str) -> LocalProtocolError:
    return LocalProtocolError(f"{field}={url!r}: {why}; {_FORMS_TEXT}", field=field, value=url)


def _check_serial(url: str, serial: str, field: str) -> str:
    if not serial:
        raise _bad(url, "the serial number is empty", field)
    if not _SERIAL.fullmatch(serial):
        raise _bad(
            url,
            f"the serial number {serial!r} has a blank or a non-printable character",
            field,
        )
    return serial


def _check_hex4(url: str, what: str, value: str, field: str) -> str:
    if not _HEX4.fullmatch(value):
        raise _bad(url, f"the {what} {value!r} is not 4 hex digits", field)
    return value.lower()


def parse_usb_url(url: str, *, field: str = "url") -> UsbSelector:
    """Check a ``usb:`` URL and return what it selects.

    Args:
        url: ``usb:serial=SERIAL``, ``usb:VID:PID`` or ``usb:VID:PID:SERIAL``.
        field: the name of the setting in error messages (``url``, ``--port``).

    Raises:
        LocalProtocolError: ``url`` is not one of those forms; the message names the
            field, the value, what is wrong and the allowed forms.
    """
    if not isinstance(url, str) or not is_usb_url(url):
        raise LocalProtocolError(
            f"{field}={url!r} is not a {USB_SCHEME} URL; {_FORMS_TEXT}", field=field, value=url
        )
    rest = url[len(USB_SCHEME) :]
    if rest.startswith("serial="):
        return UsbSelector(serial=_check_serial(url, rest[len("serial=") :], field))
    parts = rest.split(":", 2)
    if len(parts) < 2:
        raise _bad(url, "give a serial number (serial=...) or a vendor and product ID", field)
    vid = _check_hex4(url, "vendor ID", parts[0], field)
    pid = _check_hex4(url, "product ID", parts[1], field)
    serial = _check_serial(url, parts[2], field) if len(parts) == 3 else ""
    return UsbSelector(vid, pid, serial)


@dataclass(frozen=True, slots=True)
class SerialPortInfo:
    """A serial port as sysfs describes it.

    Attributes:
        name: the kernel's name, ``ttyUSB0``.
        device: the device node, ``/dev/ttyUSB0``.
        by_id: udev's stable links to it (``/dev/serial/by-id/...``), sorted.
        vid, pid: USB vendor and product ID (4 hex digits); ``""`` if not a USB port.
        serial: the USB serial number (``""``: the adapter has none, e.g. a CH340).
        manufacturer, product: the USB strings, as the adapter reports them.
        driver: the kernel driver (``ftdi_sio``, ``ch341-uart``, ``cdc_acm``, ...).
        latency_timer_ms: the receive latency timer (drivers that publish one), or None.
    """

    name: str
    device: str
    by_id: tuple[str, ...] = ()
    vid: str = ""
    pid: str = ""
    serial: str = ""
    manufacturer: str = ""
    product: str = ""
    driver: str = ""
    latency_timer_ms: int | None = None

    @property
    def is_usb(self) -> bool:
        """True for a port on a USB device (it has a vendor ID)."""
        return bool(self.vid)

    def describe(self) -> str:
        """``/dev/ttyUSB0 (0403:6001 FTDI FT232R USB UART, serial A12345)``."""
        if not self.is_usb:
            return f"{self.device} (not USB)"
        words = [f"{self.vid}:{self.pid}"]
        words += [w for w in (self.manufacturer, self.product) if w]
        serial = f"serial {self.serial}" if self.serial else "no serial number"
        return f"{self.device} ({' '.join(words)}, {serial})"

    def as_dict(self) -> dict[str, Any]:
        """The fields as JSON-ready values."""
        return {
            "name": self.name,
            "device": self.device,
            "by_id": list(self.by_id),
            "vid": self.vid,
            "pid": self.pid,
            "serial": self.serial,
            "manufacturer": self.manufacturer,
            "product": self.product,
            "driver": self.driver,
            "latency_timer_ms": self.latency_timer_ms,
        }


def read_latency_timer_ms(tty_name: str, devices_dir: str = USB_SERIAL_SYSFS) -> int | None:
    """The receive latency timer of usb-serial port ``tty_name`` in ms, or None if its
    driver publishes none (``devices_dir``: ``/sys/bus/usb-serial/devices``)."""
    path = os.path.join(devices_dir, tty_name, "latency_timer")
    try:
        with open(path, encoding="ascii") as f:
            return int(f.read().strip())
    except (OSError, ValueError):
        return None


def _read(path: str) -> str:
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            return f.read().strip()
    except OSError:
        return ""


def _usb_device_dir(device: str, sysfs: str) -> str | None:
    """The USB device (the directory with ``idVendor``) above a tty's ``device``."""
    root = os.path.realpath(sysfs)
    here = os.path.realpath(device)
    while here.startswith(root + os.sep):
        if os.path.exists(os.path.join(here, "idVendor")):
            return here
        here = os.path.dirname(here)
    return None


def _by_id_links(dev: str) -> dict[str, tuple[str, ...]]:
    """tty name -> udev's ``serial/by-id`` links to it."""
    folder = os.path.join(dev, "serial", "by-id")
    try:
        entries = sorted(os.listdir(folder))
    except OSError:
        return {}
    links: dict[str, list[str]] = {}
    for entry in entries:
        path = os.path.join(folder, entry)
        links.setdefault(os.path.basename(os.path.realpath(path)), []).append(path)
    return {name: tuple(paths) for name, paths in links.items()}


def port_info(
    tty_name: str,
    *,
    sysfs: str | None = None,
    dev: str | None = None,
    by_id: tuple[str, ...] | None = None,
) -> SerialPortInfo | None:
    """What sysfs tells about the port ``tty_name`` (``ttyUSB0``), or None if it has
    no device behind it (a virtual console, a pty) or does not exist.

    Args:
        sysfs: the sysfs root (default :data:`SYSFS`).
        dev: the device root (default :data:`DEV`).
        by_id: its ``serial/by-id`` links if already known (default: looked up).
    """
    sysfs = SYSFS if sysfs is None else sysfs
    dev = DEV if dev is None else dev
    device = os.path.join(sysfs, "class", "tty", tty_name, "device")
    if not os.path.exists(device):
        return None
    driver_link = os.path.join(device, "driver")
    driver = os.path.basename(os.path.realpath(driver_link)) if os.path.exists(driver_link) else ""
    if by_id is None:
        by_id = _by_id_links(dev).get(tty_name, ())
    usb = _usb_device_dir(device, sysfs)
    if usb is None:
        return SerialPortInfo(tty_name, os.path.join(dev, tty_name), by_id, driver=driver)
    return SerialPortInfo(
        name=tty_name,
        device=os.path.join(dev, tty_name),
        by_id=by_id,
        vid=_read(os.path.join(usb, "idVendor")).lower(),
        pid=_read(os.path.join(usb, "idProduct")).lower(),
        serial=_read(os.path.join(usb, "serial")),
        manufacturer=_read(os.path.join(usb, "manufacturer")),
        product=_read(os.path.join(usb, "product")),
        driver=driver,
        latency_timer_ms=read_latency_timer_ms(tty_name, os.path.join(sysfs, _USB_SERIAL_DEVICES)),
    )


def _natural(name: str) -> tuple[str, int]:
    """``ttyUSB2`` before ``ttyUSB10``."""
    stem = name.rstrip("0123456789")
    return (stem, int(name[len(stem) :] or -1))


def list_serial_ports(
    *, sysfs: str | None = None, dev: str | None = None, usb_only: bool = True
) -> list[SerialPortInfo]:
    """The serial ports sysfs knows, USB adapters only unless ``usb_only`` is False
    (then also the on-board UARTs and the ``ttyS`` ports the kernel always lists, which
    sysfs cannot tell from absent ones), in name order."""
    sysfs = SYSFS if sysfs is None else sysfs
    dev = DEV if dev is None else dev
    try:
        names = os.listdir(os.path.join(sysfs, "class", "tty"))
    except OSError:
        return []
    links = _by_id_links(dev)
    found = []
    for name in sorted(names, key=_natural):
        info = port_info(name, sysfs=sysfs, dev=dev, by_id=links.get(name, ()))
        if info is not None and (info.is_usb or not usb_only):
            found.append(info)
    return found


def _no_such_adapter(url: str, ports: list[SerialPortInfo]) -> OSError:
    found = "; ".join(p.describe() for p in ports) or "none (no USB serial adapter is plugged in)"
    err = OSError(f"no USB serial adapter matches {url}: found {found}")
    err.errno = errno.ENODEV
    return err


def _ambiguous(url: str, matches: list[SerialPortInfo]) -> OSError:
    named = " and ".join(p.describe() for p in matches)
    err = OSError(
        f"{url} matches {len(matches)} adapters, {named}: name one by its serial number "
        "(usb:VID:PID:SERIAL); adapters without one can only be told apart by the USB "
        "socket they are in (/dev/serial/by-path)"
    )
    err.errno = errno.ENOTUNIQ
    return err


def resolve_port(url: str, *, sysfs: str | None = None, dev: str | None = None) -> str:
    """The device path to open for ``url`` now.

    A ``usb:`` URL becomes the node of the one adapter it matches; a symlink (such as
    a ``/dev/serial/by-id/...`` link) becomes the device it points to now; anything
    else (a device node, ``COM3``, ``socket://``, ``rfc2217://``) is returned as given.
    Call it at every open: the answer changes when an adapter comes back under another
    name.

    Raises:
        LocalProtocolError: a malformed ``usb:`` URL.
        OSError: no adapter matches (``errno`` ENODEV; the message lists what is
            plugged in), or more than one does (ENOTUNIQ; the message names them), or
            there is no sysfs (not Linux: ENODEV).
    """
    if is_usb_url(url):
        selector = parse_usb_url(url)
        sysfs = SYSFS if sysfs is None else sysfs
        ttys = os.path.join(sysfs, "class", "tty")
        if not os.path.isdir(ttys):
            err = OSError(
                f"{url}: a usb: URL is found through Linux sysfs, and {ttys} is not there; "
                "name the port by its device (COM3, /dev/cu.usbserial-...) on this system"
            )
            err.errno = errno.ENODEV
            raise err
        ports = list_serial_ports(sysfs=sysfs, dev=dev)
        matches = [p for p in ports if selector.matches(p)]
        if not matches:
            raise _no_such_adapter(url, ports)
        if len(matches) > 1:
            raise _ambiguous(url, matches)
        return matches[0].device
    if "://" not in url and os.path.islink(url):
        return os.path.realpath(url)
    return url  # a device node (or COM3 on Windows) as given: realpath would mangle COM3


def port_identity(url: str) -> str:
    """What makes two URLs one port: a device path resolved through its symlinks
    (``/dev/serial/by-id/...`` is its ``/dev/ttyUSBn``), a ``usb:`` URL in its canonical
    spelling (lower-case hex), any other URL as written."""
    if is_usb_url(url):
        return str(parse_usb_url(url))
    if "://" in url:
        return url
    return os.path.realpath(url)
