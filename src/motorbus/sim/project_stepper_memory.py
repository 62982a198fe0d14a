"""The simulated project stepper's memory: four project images in RAM and in flash.

Each image is the 220 data bytes of a 0x3E dump (doc 000 A.5), laid out exactly as
the dump, so a field is written at ``dump_offset(block, k)`` less the 6-byte dump
header and a 0x3E reply is the header followed by the RAM image.  A cleared image
keeps its project number in ``[0][0]`` and is zero elsewhere (0 steps, so starting it
ends at once).  Saving copies RAM to flash, clearing zeroes both, a power cycle
reloads RAM from flash.

What the commands do with this memory, and the motion, is
``motorbus.sim.project_stepper.ProjectStepperModel``.  Pure: no clock, no I/O.
"""

from __future__ import annotations

from motorbus.protocol.base import FF_AA, check_int
from motorbus.protocol.project_stepper import (
    BASE_NUMBER,
    DUMP_HEADER_SIZE,
    DUMP_SIZE,
    MAX_PROJECT,
    OP_READ,
    ProjectDump,
    dump_offset,
)

__all__ = ["IMAGE_SIZE", "ProjectMemory", "cleared_image"]

#: Bytes of one project image: the 0x3E dump without its 6-byte header (A.5).
IMAGE_SIZE = DUMP_SIZE - DUMP_HEADER_SIZE


def cleared_image(project: int) -> bytes:
    """The image of a cleared ``project``: its number in ``[0][0]``, zero elsewhere."""
    image = bytearray(IMAGE_SIZE)
    image[dump_offset(0, BASE_NUMBER) - DUMP_HEADER_SIZE] = project
    return bytes(image)


class ProjectMemory:
    """Projects 1..4 in RAM (what commands write and 0x3E reads) and in flash."""

    __slots__ = ("_flash", "_ram")

    def __init__(self) -> None:
        self._flash: list[bytes] = [cleared_image(p) for p in range(1, MAX_PROJECT + 1)]
        self._ram: list[bytearray] = [bytearray(image) for image in self._flash]

    def put(self, project: int, block: int, k: int, data: bytes) -> None:
        """Write ``data`` into RAM at field ``k`` of ``block`` (0 = base, 1..10 = steps)."""
        off = dump_offset(block, k) - DUMP_HEADER_SIZE
        self._ram[project - 1][off : off + len(data)] = data

    def base(self, project: int, k: int) -> int:
        """The RAM byte at field ``k`` of the base block of ``project``."""
        return self._ram[project - 1][dump_offset(0, k) - DUMP_HEADER_SIZE]

    def dump_bytes(self, project: int) -> bytes:
        """The 226-byte 0x3E reply for ``project``: the dump header and its RAM image."""
        return FF_AA + bytes((OP_READ, project, 0, 0)) + bytes(self._ram[project - 1])

    def dump(self, project: int) -> ProjectDump:
        """The RAM image of ``project`` decoded (raises as ``ProjectDump.decode`` does)."""
        return ProjectDump.decode(self.dump_bytes(project))

    def save(self, project: int) -> None:
        """0x2E: copy the RAM image of ``project`` to flash."""
        self._flash[project - 1] = bytes(self._ram[project - 1])

    def clear(self, project: int) -> None:
        """0x1E: clear ``project`` in flash and in RAM."""
        self._flash[project - 1] = cleared_image(project)
        self._ram[project - 1] = bytearray(self._flash[project - 1])

    def reload(self) -> None:
        """Power-up: RAM reloads from flash."""
        self._ram = [bytearray(image) for image in self._flash]

    def image(self, project: int, *, flash: bool = False) -> bytes:
        """The 220 data bytes of ``project`` (RAM, or flash if ``flash``).

        Raises:
            LocalProtocolError: ``project`` is not 1..4.
        """
        check_int("project", project, 1, MAX_PROJECT)
        return bytes(self._flash[project - 1] if flash else self._ram[project - 1])
