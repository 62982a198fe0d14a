"""The motorbus exception tree: every exception class motorbus defines lives here.

``MotorbusError`` is the root, so ``except MotorbusError`` catches everything raised
on purpose.  The tree (python-standard bases in brackets)::

    Exception (Python standard library)
     +-- MotorbusError
         +-- LocalProtocolError [ValueError]   you asked for what the protocol cannot say
         |   +-- IdListError                    an ID list ("1-3,7") the grammar refuses
         |   +-- ControlError                   a dashboard control names no such bus/device
         |   +-- PayloadError                   a served-bus payload that does not fit
         +-- RemoteProtocolError                the peer sent a frame that does not fit
         +-- ReplyTimeoutError [TimeoutError]   no matching reply before the deadline
         +-- ArrivalTimeoutError [TimeoutError] ``move_to(wait=True)``: not there in time
         +-- NotSentError                       dropped before sending (``start_by`` passed)
         +-- GroupReadError                     ``read_statuses``: some IDs did not answer
         +-- BusClosedError [ConnectionError]   the bus or its port is closed or was lost
         +-- PortInUseError [OSError]           another open holds the port's exclusive lock
         +-- LeaseConflictError                 another owner holds the device (nothing sent)
         +-- WrongLoopError [RuntimeError]      a bus used from another event loop than its own
         +-- StreamEnded                        ``Stream.wait``: the stream ended on an error
         +-- ProjectStopped                     ``run_project`` ended by ``stop_project``
         +-- ProjectVerifyError                 a read-back project differs from the upload
         +-- RigAborted                         ``run_rig``: a ceiling tripped; all paused
         +-- ProjectInvalidError                the controller holds no valid project N
         +-- GuardError                         the guard process cannot start (no pidfds)
         +-- UsageError                         CLI: bad command-line input (exit code 2)
         +-- CommandFailed                      CLI: the command ran and failed (exit code 1)
         +-- ServeRefused [PermissionError]     a served bus lets this client only watch
         +-- ServeUnavailable [ImportError]     Eclipse Zenoh (the serve extra) is missing
         +-- ServedRefusal                      (server side) a served request refused
         +-- ServeChildError                    the dashboard's motorbus serve child failed

Two families follow h11's split:

* ``LocalProtocolError``: *you* asked for something the protocol cannot express
  (a value out of range, a wrong type).  It is also a ``ValueError`` so that
  ordinary ``except ValueError`` code keeps working.  Nothing is ever written to a
  bus when one of these is raised.
* ``RemoteProtocolError``: the *peer* sent bytes that do not make sense for the
  request that was made.  It carries the raw frame.

The bus adds timeouts and closed ports on top; the devices, streams and CLI add the
rest.  The classes are also importable from the modules that raise them
(``motorbus.streams.StreamEnded``, ``motorbus.devices.project_stepper.ProjectStopped``,
``motorbus.cli.main.UsageError``, ...).

A device fault is not an exception: the LA reports latched faults in its status
replies (``Status.faults``) and the bus publishes ``FaultChanged`` events; a request
to a faulted actuator still returns its decoded reply.
"""

from __future__ import annotations

import errno

__all__ = [
    "ArrivalTimeoutError",
    "BusClosedError",
    "CommandFailed",
    "ControlError",
    "GroupReadError",
    "GuardError",
    "IdListError",
    "LeaseConflictError",
    "LocalProtocolError",
    "MotorbusError",
    "NotSentError",
    "PayloadError",
    "PortInUseError",
    "ProjectInvalidError",
    "ProjectStopped",
    "ProjectVerifyError",
    "RemoteProtocolError",
    "ReplyTimeoutError",
    "RigAborted",
    "ServeChildError",
    "ServeRefused",
    "ServeUnavailable",
    "ServedRefusal",
    "StreamEnded",
    "UsageError",
    "WrongLoopError",
]


class MotorbusError(Exception):
    """Root of every error motorbus raises on purpose."""


class LocalProtocolError(MotorbusError, ValueError):
    """A request could not be built: a field is out of range or of the wrong type.

    The message always names the field, the value given and the allowed range.
    """

    def __init__(self, message: str, *, field: str | None = None, value: object = None) -> None:
        super().__init__(message)
        self.field = field
        self.value = value


class IdListError(LocalProtocolError):
    """An ID list that the grammar refuses.

    Attributes:
        problem: ``"syntax"`` (an item is no ID or range), ``"range"`` (an ID outside
            the allowed IDs), ``"reversed"`` (``LAST < FIRST``) or ``"duplicate"``.
        reason: what is wrong, without the caller's context, e.g.
            ``"reversed range 5-3: write 3-5"``.
        item: the offending item as written (``"5-3"``); the ID for ``"duplicate"``.
        first, last: the range's bounds (``"reversed"``), else ``None``.
    """

    def __init__(
        self,
        reason: str,
        *,
        problem: str,
        item: str,
        first: int | None = None,
        last: int | None = None,
        field: str | None = None,
        value: object = None,
    ) -> None:
        super().__init__(reason, field=field, value=value)
        self.reason = reason
        self.problem = problem
        self.item = item
        self.first = first
        self.last = last


class ControlError(LocalProtocolError):
    """A dashboard control request names an unknown bus or actuator, or a value out of
    range (``motorbus.dashboard``); nothing is sent."""


class RemoteProtocolError(MotorbusError):
    """A device sent a frame that does not fit the request it answers."""

    def __init__(self, message: str, *, raw: bytes = b"") -> None:
        super().__init__(message)
        self.raw = raw


class ReplyTimeoutError(MotorbusError, TimeoutError):
    """No matching reply arrived before the request's deadline."""


class ArrivalTimeoutError(MotorbusError, TimeoutError):
    """An actuator did not reach its target within the time allowed.

    Raised by ``InspireLA.move_to(..., wait=True)``; the actuator is not stopped.

    Attributes:
        id: the actuator's ID.
        target: the position it was sent to.
        status: the last status it reported (``status.position``, ``status.errors``).
    """

    def __init__(self, message: str, *, id: int, target: int, status: object) -> None:
        super().__init__(message)
        self.id = id
        self.target = target
        self.status = status


class NotSentError(MotorbusError):
    """A request could not start by its ``start_by`` time and was dropped; nothing was sent."""


class GroupReadError(MotorbusError):
    """A group read (``read_statuses``) where some actuators gave no status.

    Raised once every request of the group has ended (after the bus's retries), so
    the statuses that did arrive are not lost.

    Attributes:
        statuses: ``{id: Status}`` of the actuators that answered, in the order asked.
        failures: ``{id: error}`` of those that did not (``ReplyTimeoutError``,
            ``RemoteProtocolError`` or ``NotSentError``), in the order asked.
    """

    def __init__(
        self, message: str, *, statuses: dict[int, object], failures: dict[int, Exception]
    ) -> None:
        super().__init__(message)
        self.statuses = statuses
        self.failures = failures


class BusClosedError(MotorbusError, ConnectionError):
    """The bus (or its port) is closed or was lost while a request was pending."""


class PortInUseError(MotorbusError, OSError):
    """A serial port could not be opened because another open holds its exclusive lock.

    Attributes:
        url: the port as given.
        holders: ``(pid, command line)`` of each process the system names as holding
            the lock (empty where it does not tell).
    """

    def __init__(self, message: str, *, url: str = "", holders: tuple[tuple[int, str], ...] = ()):
        super().__init__(message)
        self.errno = errno.EBUSY
        self.url = url
        self.holders = holders


class LeaseConflictError(MotorbusError):
    """A motion command or a lease names a device that another owner holds.

    Nothing was sent.  Attributes: ``key`` (the device, ``"la:3"``), ``owner`` (who
    holds it) and ``refused`` (who asked).
    """

    def __init__(self, key: str, owner: str, refused: str) -> None:
        super().__init__(
            f"{key} is leased by {owner!r}, so {refused!r} may not move it (nothing "
            f"sent): one owner per device; end the lease of {owner!r} first"
        )
        self.key = key
        self.owner = owner
        self.refused = refused


class WrongLoopError(MotorbusError, RuntimeError):
    """A bus (or a device on it) was used from another event loop than the one it was
    opened on; nothing was sent.  A bus belongs to one loop (one thread): open a bus of
    its own in the other loop, or hand the work to the bus's loop
    (``asyncio.run_coroutine_threadsafe``)."""


class StreamEnded(MotorbusError):
    """Raised by ``Stream.wait`` when a stream ended on an error (the cause is chained)."""


class ProjectStopped(MotorbusError):
    """``run_project`` ended because the project was stopped (``stop_project``)."""


class ProjectVerifyError(MotorbusError):
    """The project read back through 0x3E differs from the one uploaded."""


class RigAborted(MotorbusError):
    """A rig test stopped because a ceiling tripped or an actuator faulted; every
    actuator under test was paused.  The message says which and why."""


class ProjectInvalidError(MotorbusError):
    """The controller holds no valid project of that number (cleared, never uploaded, or
    an upload that ended part way); ``check_project`` and ``motorbus project run`` refuse it."""


class GuardError(MotorbusError):
    """The guard process (``motorbus.runtime.guard``) cannot watch this program: no pidfds on
    this system (not Linux 5.3+), or the process did not start."""


class UsageError(MotorbusError):
    """Bad command-line input; reported as one line with exit code 2."""


class CommandFailed(MotorbusError):
    """The command ran and failed for the reason in the message; exit code 1."""


class PayloadError(LocalProtocolError):
    """A payload of the served-bus protocol (``motorbus.serve.keys``) that does not fit;
    names the field and the value."""


class ServeRefused(MotorbusError, PermissionError):
    """The server lets this client only watch: no motion, no leases (nothing sent)."""


class ServeUnavailable(MotorbusError, ImportError):
    """Eclipse Zenoh (the ``serve`` extra) is not installed."""


class ServeChildError(MotorbusError):
    """The dashboard's ``motorbus serve`` child ended, or never said it was ready."""


class ServedRefusal(MotorbusError):
    """Server side: a served request refused; ``payload`` is the error reply sent to the
    client (``motorbus.serve.keys.error_payload``)."""

    def __init__(self, payload: dict[str, object]) -> None:
        super().__init__(str(payload["message"]))
        self.payload = payload
