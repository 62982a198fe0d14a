"""The 9-byte ``FF AA`` 4-axis stepper controller as an async device."""

from __future__ import annotations

import asyncio
import contextlib
import logging

from motorbus.bus.bus import Bus, Priority
from motorbus.bus.events import QuadDone
from motorbus.errors import LeaseConflictError, ReplyTimeoutError
from motorbus.protocol import quad_stepper as q
from motorbus.protocol import safety
from motorbus.protocol.base import WAIT_TIMEOUT_MAX_S, check_flag, check_timeout
from motorbus.validation import check_device_bus

__all__ = ["QuadStepper"]

log = logging.getLogger("motorbus.quad_stepper")

#: Host-side ceiling on waiting for a "done" reply when the caller gives none:
#: the manual documents no duration (A1-09), and a long move at low speed can take
#: minutes, so the default is generous; pass ``timeout`` for anything tighter.
DEFAULT_DONE_TIMEOUT_S = 600.0
#: The controller's device key (one per bus).
KEY = q.StopAll.family.value


class QuadStepper:
    """A 4-axis stepper controller on a bus.

    Every method sends one command and returns its decoded acknowledgement; the ones
    that start motion can also wait for the controller's "done" reply.

    Args:
        bus: an open :class:`~motorbus.bus.bus.Bus` carrying ``Family.QUAD_STEPPER``.
    """

    def __init__(self, bus: Bus) -> None:
        check_device_bus(bus)
        self.bus = bus
        # A single-motor run's done reply is addressed to 0x00, not to the motor (A1-02):
        # with two awaited runs in flight it could not be attributed, so awaited runs
        # take turns.
        self._run_lock = asyncio.Lock()

    def safe_stop_commands(self) -> list[q.QuadCommand]:
        """The commands that stop every motor of this controller, as values (stop all)."""
        return [cmd for cmd in safety.safe_stop_commands(KEY) if isinstance(cmd, q.QuadCommand)]

    async def release(self, *, hold: bool = False) -> None:
        """End the program's hold on this controller (motion started outside any lease).

        A run, a run of all motors or homing started outside an explicit lease
        (``bus.lease``) is owned by the bus's implicit lease, and the bus sends stop all
        when it closes.  ``release()`` sends it now; ``release(hold=True)`` ends the
        ownership on purpose and sends nothing: what runs keeps running, also after the
        bus closes.

        Raises:
            LeaseConflictError: an explicit lease holds the controller (release that).
        """
        await self.bus.release([KEY], hold=hold)

    async def configure(
        self,
        motor: int,
        *,
        subdivision: int,
        step_angle_x100: int,
        pulses: int,
        direction: q.RotationDirection | int = q.RotationDirection.FORWARD,
        start_hz: int,
        accel_hz: int,
        speed_rpm: int,
    ) -> None:
        """Set a motor's microstepping, run length, direction, start frequency, ramp and speed.

        The settings are lost at power-off unless :meth:`save` is called.

        Args:
            motor: 1..4.
            subdivision: microsteps per full step, 1..65535.
            step_angle_x100: step angle in 0.01 degree (1.8 deg -> 180), 1..255.
            pulses: run length in pulses, 0..16777215 (A1-05).
            direction: FORWARD or REVERSE.
            start_hz: start (and homing) frequency in Hz, 0..65535.
            accel_hz: acceleration/deceleration setting, 0..65535 (unit not documented).
            speed_rpm: run speed in RPM, 0..65535.

        All four commands are validated before the first is sent.
        """
        commands = [
            q.MotorSetup(motor, subdivision, step_angle_x100),
            q.RunPulses(motor, pulses),
            # The command validates and converts the direction (an int or the enum).
            q.DirectionAndStartFrequency(motor, direction, start_hz),  # type: ignore[arg-type]
            q.AccelAndSpeed(motor, accel_hz, speed_rpm),
        ]
        for cmd in commands:
            await self.bus.request(cmd)

    async def run(
        self,
        motor: int,
        *,
        wait: bool = True,
        timeout: float | None = None,
        keep_running: bool = False,
    ) -> None:
        """Start a motor's configured run; with ``wait``, return when it reports done.

        **Awaited runs take turns.**  The controller answers a single-motor run, and
        reports it done, with motor byte 0x00 rather than the motor's number (A1-02 in
        docs/protocols.md), so a done reply can only be attributed while one awaited
        run is in flight: two ``run(..., wait=True)`` under ``asyncio.gather`` run one
        after the other, on one controller or across ``QuadStepper`` handles of it.

        To run axes together: start them with ``wait=False`` (each returns on its ack
        and the motors run at once) and wait for them yourself, e.g. through
        ``bus.events.subscribe(QuadDone)`` created before the runs, or use
        :meth:`run_all` (all four, no done reply documented, A1-04).

        A run whose done reply does not come in time is stopped (stop that motor; if
        that is not acknowledged, stop all) unless ``keep_running`` (then it runs on,
        also after the bus closes: the program's hold on it ends with ``hold``).  A cancelled call
        (Ctrl-C, an enclosing timeout) always sends the stop before the cancellation
        goes on.

        Args:
            motor: 1..4.
            wait: wait for the done reply (default) or return on the ack.
            timeout: seconds to wait for done, 0..86400; default ``DEFAULT_DONE_TIMEOUT_S``
                (600 s: the manual gives no duration and a slow long move can take
                minutes).
            keep_running: on a timeout, leave the motor running (the error says how
                to stop it).

        Raises:
            ReplyTimeoutError: no ack, or no done reply within ``timeout`` seconds;
                the message says whether the motor was stopped.
        """
        cmd = q.Run(motor)
        check_flag("wait", wait)
        check_flag("keep_running", keep_running)
        limit = (
            DEFAULT_DONE_TIMEOUT_S
            if timeout is None
            else check_timeout("timeout", timeout, WAIT_TIMEOUT_MAX_S)
        )
        try:
            if not wait:
                await self.bus.request(cmd)
                return
            async with self._run_lock:
                with self.bus.events.subscribe(QuadDone, lambda e: e.kind == "run") as sub:
                    await self.bus.request(cmd)
                    try:
                        await sub.next(limit)
                    except ReplyTimeoutError:
                        waited = f"motor {motor} did not report done within {limit:g} s"
                        if keep_running:
                            await self._keep_running()
                            raise ReplyTimeoutError(
                                f"{waited}: still running; `motorbus quad stop {motor}` ends it"
                            ) from None
                        stopped = await self._stop_after(cmd)
                        raise ReplyTimeoutError(f"{waited}: {stopped}") from None
        except asyncio.CancelledError:
            await self._stop_after(cmd)
            raise

    async def _keep_running(self) -> None:
        """The caller chose to leave the motion running: end the implicit lease with
        hold (an explicit lease is its owner's to end)."""
        with contextlib.suppress(LeaseConflictError):
            await self.release(hold=True)

    async def _stop_after(self, run: q.Run) -> str:
        """Stop the motor of ``run`` after the run was abandoned (stop all if that fails);
        say what was done.  The stops are the lease keeper's (the one sender of safe
        actions): emergency priority with their retries; Ctrl-C and a cancellation wait
        for them."""
        keeper = self.bus.lease_keeper
        motor = run.motor
        # What ends this motion (that motor's stop); the whole safe action if unknown.
        stops = safety.motion_stops(run) or keeper.safe_commands(KEY)
        # The motor's stop, then stop all if that fails: one shielded ending, so that a
        # second cancellation cannot fall between the two.
        tried = await keeper.stop_shielded(
            stops, keeper.safe_commands(KEY), who=f"motor {motor}'s run"
        )
        # The last step tried failed only if neither the stop nor the stop all went.
        failed = next((r for r in tried[-1] if isinstance(r, BaseException)), None)
        if failed is not None:
            return f"the stop got no answer ({failed}): it may still be running"
        if len(tried) == 1:
            return f"stopped it (stop 0x{q.CMD_STOP:02X} to motor {motor} sent)"
        return f"stopped it (stop 0x{q.CMD_STOP:02X} to all motors sent)"

    async def run_all(self) -> None:
        """Start all four motors (the manual documents no done reply for this, A1-04)."""
        await self.bus.request(q.RunAll())

    async def stop(self, motor: int) -> None:
        """Stop one motor at once."""
        await self.bus.request(q.Stop(motor), priority=Priority.HIGH)

    async def stop_all(self) -> None:
        """Stop every motor; jumps the bus queue."""
        await self.bus.request(q.StopAll(), priority=Priority.EMERGENCY)

    async def home(self, motor: int, stop_input: int) -> None:
        """Start homing in the configured direction until input YL``stop_input`` (1..13).

        ``stop_input=0`` starts a homing run that only a stop ends (A1-10); pass it
        explicitly if that is what you want.
        """
        await self.bus.request(q.Home(motor, stop_input))

    async def led(self, led: int, on: bool, *, wait: bool = True, timeout: float = 1.0) -> None:
        """Switch LED ``led`` (1..4, 5 = all); with ``wait``, return after its done reply."""
        cmd = q.SetLed(led, on)
        check_flag("wait", wait)
        check_timeout("timeout", timeout, WAIT_TIMEOUT_MAX_S)
        if not wait:
            await self.bus.request(cmd)
            return
        with self.bus.events.subscribe(QuadDone, lambda e: e.kind == "led" and e.led == led) as sub:
            await self.bus.request(cmd)
            await sub.next(timeout)

    async def save(self) -> None:
        """Save the parameters to the controller's flash (reloaded at power-up)."""
        await self.bus.request(q.Save())
