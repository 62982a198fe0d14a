"""A fake sysfs and /dev, laid out as Linux lays out USB serial adapters.

``/sys/class/tty/NAME`` is a link into ``/sys/devices``; its ``device`` link leads to
the usb-serial port (``ttyUSB``: FTDI, CH340) or to the USB interface itself
(``ttyACM``: CDC-ACM); the USB device above holds ``idVendor`` and the strings.  Only
the files motorbus reads are made.  ``/dev/NAME`` is an empty file, or a link to a
real pty when a test opens it.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Adapter:
    vid: str
    pid: str
    serial: str
    manufacturer: str
    product: str
    driver: str  # the tty's driver: ftdi_sio, ch341-uart, cdc_acm
    latency_ms: int | None = None

    @property
    def by_id_name(self) -> str:
        maker = self.manufacturer or self.vid  # udev's fallback when there is no string
        words = "_".join(f"{maker} {self.product}".split())
        tail = f"_{self.serial}" if self.serial else ""
        port = "-if00" if self.driver == "cdc_acm" else "-if00-port0"
        return f"usb-{words}{tail}{port}"


FT232R = Adapter("0403", "6001", "A12345", "FTDI", "FT232R USB UART", "ftdi_sio", 16)
FT232R_B = Adapter("0403", "6001", "B67890", "FTDI", "FT232R USB UART", "ftdi_sio", 1)
CH340 = Adapter("1a86", "7523", "", "", "USB2.0-Serial", "ch341-uart")
CDC_ACM = Adapter("2e8a", "000a", "E6614C311B4A", "Raspberry Pi", "Pico", "cdc_acm")


class FakeSysfs:
    """``root/sys`` and ``root/dev``; :meth:`plug` and :meth:`unplug` adapters."""

    def __init__(self, root: Path) -> None:
        self.sys = root / "sys"
        self.dev = root / "dev"
        self.by_id = self.dev / "serial" / "by-id"
        (self.sys / "class" / "tty").mkdir(parents=True)
        (self.sys / "bus" / "usb-serial" / "devices").mkdir(parents=True)
        self.by_id.mkdir(parents=True)
        self._usb_dirs: dict[str, Path] = {}

    def plug(
        self, adapter: Adapter, tty: str, *, usb_port: str = "1-1", node: str | None = None
    ) -> Path:
        """Add ``adapter`` as ``tty`` in USB socket ``usb_port``; return its /dev node.

        ``node``: make the /dev node a link to this path (a pty) instead of a file.
        """
        usb = self.sys / "devices" / "pci0000:00" / "0000:00:14.0" / "usb1" / usb_port
        iface = usb / f"{usb_port}:1.0"
        iface.mkdir(parents=True)
        attrs = {"idVendor": adapter.vid, "idProduct": adapter.pid}
        attrs |= {"manufacturer": adapter.manufacturer, "product": adapter.product}
        if adapter.serial:
            attrs["serial"] = adapter.serial
        for name, value in attrs.items():
            if value:
                (usb / name).write_text(value + "\n")
        if adapter.driver == "cdc_acm":
            port = iface  # the tty hangs off the interface
            (iface / "driver").symlink_to(self._driver("usb", "cdc_acm"))
        else:
            port = iface / tty
            port.mkdir()
            (iface / "driver").symlink_to(self._driver("usb", adapter.driver.split("-")[0]))
            (port / "driver").symlink_to(self._driver("usb-serial", adapter.driver))
            (self.sys / "bus" / "usb-serial" / "devices" / tty).symlink_to(port)
            if adapter.latency_ms is not None:
                (port / "latency_timer").write_text(f"{adapter.latency_ms}\n")
        class_dev = port / "tty" / tty
        class_dev.mkdir(parents=True)
        (class_dev / "device").symlink_to(port)
        (self.sys / "class" / "tty" / tty).symlink_to(class_dev)
        path = self.dev / tty
        if node is None:
            path.write_text("")
        else:
            path.symlink_to(node)
        link = self.by_id / adapter.by_id_name
        if link.is_symlink():
            link.unlink()  # two alike: udev's link names the one found last
        link.symlink_to(Path("..") / ".." / tty)
        self._usb_dirs[tty] = usb
        return path

    def unplug(self, tty: str) -> None:
        """Remove ``tty``'s adapter, its /dev node and its by-id link."""
        for link in self.by_id.iterdir():
            if Path(os.readlink(link)).name == tty:
                link.unlink()
        (self.sys / "class" / "tty" / tty).unlink()
        serial_link = self.sys / "bus" / "usb-serial" / "devices" / tty
        if serial_link.is_symlink():
            serial_link.unlink()
        shutil.rmtree(self._usb_dirs.pop(tty))
        (self.dev / tty).unlink()

    def add_uart(self, tty: str = "ttyS0") -> None:
        """An on-board UART: a tty with a device, but no USB device above it."""
        port = self.sys / "devices" / "platform" / "serial8250" / tty
        class_dev = port / "tty" / tty
        class_dev.mkdir(parents=True)
        (port / "driver").symlink_to(self._driver("platform", "serial8250"))
        (class_dev / "device").symlink_to(port)
        (self.sys / "class" / "tty" / tty).symlink_to(class_dev)
        (self.dev / tty).write_text("")

    def add_virtual(self, tty: str = "tty0") -> None:
        """A virtual console: in class/tty, with no device."""
        (self.sys / "devices" / "virtual" / "tty" / tty).mkdir(parents=True)
        (self.sys / "class" / "tty" / tty).symlink_to(self.sys / "devices/virtual/tty" / tty)

    def _driver(self, bus: str, name: str) -> Path:
        path = self.sys / "bus" / bus / "drivers" / name
        path.mkdir(parents=True, exist_ok=True)
        return path
