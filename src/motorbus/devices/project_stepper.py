"""The 11-byte ``FF AA`` stepper "project" controller as an async device."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time

from motorbus.bus.bus import Bus, Priority
from motorbus.bus.events import ProjectFinished, Subscription
from motorbus.bus.leases import PROGRAM, Lease
from motorbus.errors import (
    BusClosedError,
    LeaseConflictError,
    LocalProtocolError,
    MotorbusError,
    ProjectInvalidError,
    ProjectStopped,
    ProjectVerifyError,
    RemoteProtocolError,
    ReplyTimeoutError,
)
from motorbus.lifecycle import deferred_interrupts
from motorbus.protocol import project_stepper as ps
from motorbus.protocol import safety
from motorbus.protocol.base import WAIT_TIMEOUT_MAX_S, check_flag, check_timeout
from motorbus.validation import check_device_bus

__all__ = ["ProjectInvalidError", "ProjectStepper", "ProjectStopped", "ProjectVerifyError"]

log = logging.getLogger("motorbus.project_stepper")

#: Host-side ceiling on a project run when the caller gives none (the manual gives no
#: figure; A0-06 asks for a per-run timeout).
DEFAULT_RUN_TIMEOUT_S = 600.0
#: After a stop, how long a new run waits before it starts: a controller may answer the
#: stop with a late EE DD (A0-06 leaves it open), which must not end the next run's wait.
STOP_SETTLE_S = 0.5
#: The controller's device key (one per bus).
KEY = ps.StartProject.family.value
#: What to tell a user who let a timed-out project keep running.
STOP_HINT = "`motorbus project stop` ends it"


class ProjectStepper:
    """A stepper project controller on a bus: up to 4 projects of 10 steps.

    Args:
        bus: an open bus carrying ``Family.PROJECT_STEPPER``.
        motor: the motor byte of motor-addressed commands (default 0x03, A0-02).
    """

    def __init__(self, bus: Bus, *, motor: int = ps.DEFAULT_MOTOR) -> None:
        check_device_bus(bus)
        ps.ManualStop(motor=motor)  # validates the motor byte (refuses 0x00 and opcodes)
        self.bus = bus
        self.motor = motor
        # The subscription a run_project() is waiting on; stop_project() closes it,
        # which ends that wait at once (no helper task, so nothing can be orphaned).
        self._run_sub: Subscription[ProjectFinished] | None = None
        self._last_stop = -STOP_SETTLE_S
        self._stop_requested = False

    def safe_stop_commands(self) -> list[ps.ProjectStepperCommand[object]]:
        """The commands that stop everything this controller may be doing, as values:
        stop the running project (0x5E), then stop manual motion of its motor (0x0D)."""
        commands = safety.safe_stop_commands(KEY, "pause", motor=self.motor)
        return [cmd for cmd in commands if isinstance(cmd, ps.ProjectStepperCommand)]

    async def release(self, *, hold: bool = False) -> None:
        """End the program's hold on this controller (motion started outside any lease).

        A project run, a jog, a single run or homing started outside an explicit lease
        (``bus.lease``) is owned by the bus's implicit lease, and the bus stops the
        controller (``safe_stop_commands``) when it closes.  ``release()`` stops it
        now; ``release(hold=True)`` ends the ownership on purpose and sends nothing:
        what runs keeps running, also after the bus closes.

        Raises:
            LeaseConflictError: an explicit lease holds the controller (release that).
        """
        await self.bus.release([KEY], hold=hold)

    # -- projects ------------------------------------------------------------------

    async def upload(
        self, project: ps.Project, *, save: bool = True, verify: bool = True
    ) -> ps.ProjectDump | None:
        """Program ``project`` with the exact command sequence of the manual (A.6).

        An upload cannot half-happen silently.  If it ends part way (cancelled by
        Ctrl-C or a timeout, or a frame failed), the project on the controller holds a
        mix of the old and the new project, which would read back and run as if valid.
        So the upload then clears it (0x1E, the manual's only way to mark a project
        empty: RAM and flash), jumping the queue, with Ctrl-C deferred while that one
        frame is on the wire: one request more, about 20 ms at 9600 baud, bounded by
        the bus's reply timeout.  A cleared project has 0 steps: ``read_project(...)
        .to_project()``, a verify and ``check_project`` refuse it, and ``motorbus
        project read``/``run`` exit 1.  Upload it again to use it.

        A program killed outright mid-upload (SIGKILL, the OOM killer) runs none of
        that.  So while it writes, the upload holds a lease on the controller (owner
        ``"upload project N"``, ``bus.leases``) whose safe action is that clear: a guard
        process (``motorbus.run(main(), guard=True)``, ``--guard``) sends it when the
        program dies holding it.  The bus closing under the upload sends it too.  A
        completed upload ends the lease with hold (nothing sent, before the verify);
        one that ends part way ends it once the clear above was sent, so the clear goes
        out once.  If the program had moved the controller outside any lease (the
        bus's implicit lease, owner ``"program"``), the upload's lease also owes its
        stop (0x5E, 0x0D) and hands the controller back to the implicit lease at the
        end: the bus's close still stops it.

        The upload is refused, nothing sent, while another lease holds the controller
        (``LeaseConflictError`` naming the holder): it does not join, since a project
        written under another owner's run (a rig's, a CLI command's) could be cleared
        by the upload's safe end in the middle of it.  Upload before taking a lease on
        the controller, or release it first.  While the upload writes, motion of the
        controller from elsewhere in the program is refused the same way.

        Args:
            project: the project value (number 1..4, motor configuration, 1..10 steps).
            save: send 0x2E afterwards so the project survives a power cycle.
            verify: read it back with 0x3E and compare.

        Returns:
            The read-back dump when ``verify``, else ``None``.

        Raises:
            LeaseConflictError: another lease holds the controller (nothing sent).
            asyncio.CancelledError: cancelled part way; its message names the project
                and how far the upload got, e.g. "project 1: upload interrupted after
                12 of 28 frames; the project on the device is invalid (cleared, 0x1E
                sent): upload it again".  It stays a ``CancelledError`` so that
                cancellation, ``asyncio.timeout`` and task groups work as usual.
            ProjectVerifyError: the read-back differs from ``project``.
            RemoteProtocolError: a 0x7E/0x8E reply names another project than the one
                selected (A0-03).  This and any other error part way carry a note
                (``add_note``, also logged) saying how far it got and that the project
                was cleared.
        """
        if not isinstance(project, ps.Project):
            raise LocalProtocolError(
                f"project must be a project_stepper.Project, got {project!r}", field="project"
            )
        check_flag("save", save)
        check_flag("verify", verify)
        commands = ps.project_commands(project, self.motor)
        if save:
            commands.append(ps.SaveProject(project.number))
        lease, program_held = self._upload_lease(project.number)
        done = 0
        try:
            for cmd in commands:
                reply = await self._upload_frame(cmd, lease)
                done += 1
                echoed = getattr(reply, "project", None)
                if isinstance(cmd, (ps.StepLoop, ps.RepeatCount)) and echoed not in (
                    None,
                    project.number,
                ):
                    raise RemoteProtocolError(
                        f"{type(cmd).__name__} acted on project {echoed}, "
                        f"not {project.number} (A0-03)",
                        raw=getattr(reply, "raw", b""),
                    )
        except asyncio.CancelledError as err:
            what = await self._invalidate(lease, project.number, done, len(commands), "interrupted")
            raise asyncio.CancelledError(what) from err
        except (MotorbusError, OSError) as err:
            if done == 0 and isinstance(err, LocalProtocolError):
                raise  # refused before anything was sent: the project is untouched
            what = await self._invalidate(lease, project.number, done, len(commands), "failed")
            err.add_note(what)
            raise
        finally:
            # Complete, or the clear was sent (or tried) above: nothing more to send.
            await self._end_upload_lease(lease, program_held)
        if not verify:
            return None
        dump = await self.read_project(project.number)
        try:
            read_back = dump.to_project()
        except LocalProtocolError as err:
            # The dump has no checksum: a corrupted byte can hold a field no project can
            # have.  That is the device's (or the line's) fault, not the caller's.
            raise ProjectVerifyError(
                f"project {project.number} read back is not a valid project: {err}"
            ) from err
        if read_back != project:
            raise ProjectVerifyError(
                f"project {project.number} read back differs: sent {project}, read {read_back}"
            )
        return dump

    def _upload_lease(self, number: int) -> tuple[Lease, bool]:
        """Lease the controller for an upload of project ``number``; its safe action is
        the clear (0x1E), after the stop if the program had moved the controller.
        Returns the lease, and whether the implicit lease held the controller before."""
        program_held = any(i.key == KEY and i.owner == PROGRAM for i in self.bus.leases)
        clear = ps.ClearProject(number)
        safe = (*self.safe_stop_commands(), clear) if program_held else (clear,)
        lease = self.bus.lease(
            KEY, owner=f"upload project {number}", safe_commands=safe, bind=False
        )
        return lease, program_held

    async def _upload_frame(self, cmd: ps.ProjectStepperCommand[object], lease: Lease) -> object:
        """Send one upload frame while the upload's lease lasts.  A bus that closes
        ends the lease with its safe action, the clear: a frame still queued then is
        dropped unsent (``refresh``), so that nothing of the upload follows the clear."""
        dropped = False

        def refresh() -> ps.ProjectStepperCommand[object] | None:
            nonlocal dropped
            dropped = not lease.active
            return None if dropped else cmd

        future = self.bus.submit(cmd, refresh=refresh) if lease.active else None
        if future is not None:
            try:
                reply = await future
            except asyncio.CancelledError:
                future.cancel()  # queued: dropped; written: its reply still holds the bus
                raise
            if not dropped:
                return reply
        raise BusClosedError(
            f"bus {self.bus.name} is closing: it ended the upload's lease, so "
            f"{type(cmd).__name__} was not sent"
        )

    async def _end_upload_lease(self, lease: Lease, program_held: bool) -> None:
        """End an upload's lease without sending anything: hold, or back to the
        implicit lease if that held the controller before (its close stops it)."""
        if program_held and lease.active:
            self.bus.hand_over(lease, [KEY])
        await lease.release(hold=True)

    async def _invalidate(self, lease: Lease, number: int, done: int, total: int, how: str) -> str:
        """Clear project ``number`` after an upload ended part way; say what happened."""
        head = f"project {number}: upload {how} after {done} of {total} frames; "
        if not lease.active:
            # The bus ended the lease as it closed, with its safe action: the clear.
            what = (
                f"{head}the bus closed under it and sent the upload's safe action, the "
                "clear (0x1E; a failure is logged): the project on the device is invalid: "
                "upload it again"
            )
            log.warning("%s", what)
            return what
        with deferred_interrupts():
            try:
                # The upload's safe action, sent by the one sender of safe actions.
                (result,) = await self.bus.lease_keeper.send_stop(
                    [ps.ClearProject(number)], who=f"project {number}'s upload"
                )
                if isinstance(result, BaseException):
                    raise result
            except (MotorbusError, OSError) as err:
                what = (
                    f"{head}clearing it (0x1E) failed ({err}): the project on the device may "
                    "mix the old and the new project; do not run it, clear or upload it again"
                )
            except asyncio.CancelledError:
                what = (
                    f"{head}cancelled again while clearing it (0x1E): the project on the "
                    "device may mix the old and the new project; do not run it, clear or "
                    "upload it again"
                )
            else:
                what = (
                    f"{head}the project on the device is invalid (cleared, 0x1E sent): "
                    "upload it again"
                )
        log.warning("%s", what)
        return what

    async def check_project(self, number: int) -> ps.Project:
        """Read project ``number`` back and return it; refuse one that is not valid.

        Raises:
            ProjectInvalidError: the controller holds no valid project ``number``
                (cleared, never uploaded, or an upload that ended part way).
        """
        dump = await self.read_project(number)
        try:
            return dump.to_project()
        except LocalProtocolError as err:
            raise ProjectInvalidError(
                f"project {number} on the controller is not a valid project (cleared, or "
                f"an upload ended part way): {err}; upload it again"
            ) from err

    async def read_project(self, number: int) -> ps.ProjectDump:
        """Read project ``number`` (1..4) back: the 226-byte 0x3E dump, decoded."""
        dump = await self.bus.request(ps.ReadProject(number))
        return dump

    async def save_project(self, number: int) -> None:
        """Save project ``number`` to the controller's flash."""
        await self.bus.request(ps.SaveProject(number))

    async def clear_project(self, number: int) -> None:
        """Clear project ``number``'s parameters."""
        await self.bus.request(ps.ClearProject(number))

    async def start_project(self, number: int) -> None:
        """Start project ``number`` and return at once (``EE DD`` comes as an event)."""
        await self.bus.request(ps.StartProject(number))

    async def run_project(
        self, number: int, *, timeout: float | None = None, keep_running: bool = False
    ) -> None:
        """Start project ``number`` and return when it finishes (the controller's ``EE DD``).

        The event subscription is registered before the start command is written, so
        a project that ends at once is not missed.

        A run that does not finish in time is stopped (0x5E) unless ``keep_running``.
        A cancelled run (Ctrl-C, an enclosing timeout) always sends the stop before the
        cancellation goes on: a project nobody waits for must not keep the motor going.

        Args:
            number: the project, 1..4.
            timeout: seconds to wait for ``EE DD``, 0..86400 (default 600).
            keep_running: on timeout, leave the project running instead of stopping it
                (also after the bus closes: it ends the program's hold with ``hold``).

        Raises:
            ReplyTimeoutError: no ``EE DD`` within ``timeout``; the message says whether
                the project was stopped ("stopped it (0x5E sent)") or is still running.
            ProjectStopped: ``stop_project`` was called meanwhile.
        """
        limit = (
            DEFAULT_RUN_TIMEOUT_S
            if timeout is None
            else check_timeout("timeout", timeout, WAIT_TIMEOUT_MAX_S)
        )
        check_flag("keep_running", keep_running)
        start = ps.StartProject(number)  # validates the number before anything is sent
        self._stop_requested = False
        # A controller may send EE DD after a stop too (A0-06): let that one come and go
        # before a new run starts, so it cannot end the new run's wait.
        settle = self._last_stop + STOP_SETTLE_S - time.monotonic()
        if settle > 0:
            await asyncio.sleep(settle)
        # An EE DD is this run's only if it was read after the start's acknowledgement:
        # one read before it came from before the start (a stop's, another program's).
        # Judged as each is published, in the order read: a loaded host reads the ack
        # and a short project's EE DD in one chunk, and its task resumes after both.
        acknowledged: asyncio.Future[object] | None = None  # the start's reply
        before_start = 0

        def after_the_start(_: ProjectFinished) -> bool:
            nonlocal before_start
            if acknowledged is not None and acknowledged.done():
                return True
            before_start += 1
            return False

        with self.bus.events.subscribe(ProjectFinished, after_the_start) as sub:
            self._run_sub = sub
            try:
                acknowledged = self.bus.submit(start)
                await acknowledged
                if before_start:
                    log.debug(
                        "project %d: ignored %d EE DD from before its start", number, before_start
                    )
                try:
                    await sub.next(limit)
                except StopAsyncIteration:
                    if not self._stop_requested:  # closed by someone else than stop_project
                        raise MotorbusError(
                            f"project {number}: the wait for its end was closed"
                        ) from None
                    raise ProjectStopped(
                        f"project {number} was stopped before it finished"
                    ) from None
                except ReplyTimeoutError:
                    waited = f"project {number} did not finish (no EE DD) within {limit:g} s"
                    if keep_running:
                        await self._keep_running()
                        raise ReplyTimeoutError(f"{waited}: still running; {STOP_HINT}") from None
                    raise ReplyTimeoutError(f"{waited}: {await self._stop_after(start)}") from None
            except asyncio.CancelledError:
                await self._stop_after(start)
                raise
            finally:
                self._run_sub = None

    async def _keep_running(self) -> None:
        """The caller chose to leave the motion running: end the implicit lease with
        hold (an explicit lease is its owner's to end)."""
        with contextlib.suppress(LeaseConflictError):
            await self.release(hold=True)

    async def _stop_after(self, start: ps.StartProject) -> str:
        """Stop the run of ``start`` after it ended without ``EE DD``; say what happened.

        The stop is the lease keeper's (the one sender of safe actions): what ends the
        motion ``start`` began (``safety.motion_stops``: stop project, 0x5E), at
        emergency priority with its retries; a failure is logged there.  Ctrl-C and a
        cancellation wait for it."""
        self._last_stop = time.monotonic()
        keeper = self.bus.lease_keeper
        # What ends this motion; the controller's whole safe action if that were unknown.
        stops = safety.motion_stops(start) or keeper.safe_commands(KEY, motor=self.motor)
        [results] = await keeper.stop_shielded(stops, who=f"project {start.project}'s run")
        for result in results:
            if isinstance(result, BaseException):
                return f"the stop (0x5E) failed ({result}): it may still be running; {STOP_HINT}"
        return "stopped it (0x5E sent)"

    async def stop_project(self) -> None:
        """Stop the running project (0x5E); jumps the queue.  No ``EE DD`` follows.

        A ``run_project`` waiting on this controller ends with ``ProjectStopped``.
        """
        self._stop_requested = True
        self._last_stop = time.monotonic()
        if self._run_sub is not None:
            self._run_sub.close()  # ends the run's wait with StopAsyncIteration
        await self.bus.request(ps.StopProject(), priority=Priority.EMERGENCY)

    # -- manual motion and settings ---------------------------------------------------

    async def jog(self, *, forward: bool = True) -> None:
        """Jog continuously (speed of project 1 step 1, A0-12) until ``stop``."""
        check_flag("forward", forward)
        cmd = ps.JogForward(motor=self.motor) if forward else ps.JogReverse(motor=self.motor)
        await self.bus.request(cmd)

    async def single_run(self) -> None:
        """One run with the distance and speed of project 1 step 1 (A0-12)."""
        await self.bus.request(ps.SingleRun(motor=self.motor))

    async def home(self) -> None:
        """Run in reverse until input IN5 is active (manual homing, 0x0F)."""
        await self.bus.request(ps.Home(motor=self.motor))

    async def stop(self) -> None:
        """Stop manual motion (0x0D); jumps the queue."""
        await self.bus.request(ps.ManualStop(motor=self.motor), priority=Priority.EMERGENCY)

    async def set_stop_mode(self, mode: ps.StopBehavior | int) -> None:
        """0 = decelerate, 1 = stop immediately."""
        # StopMode validates and converts the mode (an int or the enum).
        await self.bus.request(ps.StopMode(mode, motor=self.motor))  # type: ignore[arg-type]

    async def set_output(self, port: ps.OutputPort | int, active: bool) -> None:
        """Switch an output: port 1..3 = OUTn, 4 = all three, 5 = LED1 and LED2."""
        level = ps.OutputLevel.ACTIVE if check_flag("active", active) else ps.OutputLevel.INACTIVE
        await self.bus.request(ps.SetOutput(port, level))  # type: ignore[arg-type]

    async def read_input(self, number: int) -> bool:
        """True if input IN``number`` (1..5) is active."""
        value: bool = await self.bus.request(ps.ReadInput(number))
        return value

    async def set_mode4(self, value: int) -> None:
        """The undocumented "mode 4" setting, raw 0..2 (A0-13)."""
        await self.bus.request(ps.SetMode4(value))

    async def set_power_on_homing(self, enabled: bool) -> None:
        """Home automatically at power-up."""
        await self.bus.request(ps.SetPowerOnHoming(enabled))
