"""``ServoOutput``: what the live runtime drives, one frame of contractions at a time.

Built from a :class:`~livebridge.servo.rig.Rig` and the basis's muscle
names; opens each bus by its URL. Lifecycle (as ros2_control's hardware
components)::

    out = ServoOutput(rig, muscle_names)
    out.configure()          # open buses, find and check servos, set profiles/limits
    out.activate()           # torque on holding the present position; soft start from there
    out.send(x, t)           # per frame: x (n_muscles,) -> safe raw targets -> one write per bus
    out.estop()              # latch: torque off / stop pulses / go home
    out.deactivate()         # torque off, buses stay open
    out.close()              # ease to neutral, torque off, release the ports

A bus that fails (a vanished USB adapter) is reported in :attr:`events` and
left out; the others keep running.
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace

import numpy as np

from livebridge.devices.registry import open_bus
from livebridge.servo.bus import ServoSetup, ServoStatus
from livebridge.servo.rig import Rig
from livebridge.servo.safety import to_raw_int


class ServoOutput:
    """Contractions -> servos, through the rig's mapping and the safety stage.

    Parameters
    ----------
    rig : Rig
    muscle_names : sequence of str
        Order of the contraction vectors given to :meth:`send`.
    poll_every : int
        Read servo state back every this many frames.
    bus_options : dict, optional
        Bus name -> keyword options for its driver (e.g. ``{"head": {"status_every": 5}}``).
    """

    def __init__(self, rig: Rig, muscle_names, clock=time.monotonic, log=None, poll_every: int = 1,
                 bus_options: dict | None = None):
        self.rig = rig
        self.muscle_names = tuple(muscle_names)
        self.clock = clock
        self.log = log or (lambda message: None)
        self.poll_every = max(1, int(poll_every))
        self.bus_options = bus_options or {}
        self.mapper = rig.safety(self.muscle_names)
        self.buses: dict = {}
        self.state = None
        self.events: list[tuple[float, str, str]] = []
        self.failed_buses: set[str] = set()
        self.frames = 0
        self.last_targets: np.ndarray | None = None
        self._by_bus = {name: [i for i, s in enumerate(rig.servos) if s.bus == name] for name in rig.buses}
        # a serial bus is half duplex: a write from the frame thread waits for a status poll from another thread
        self._wire = threading.Lock()

    @property
    def servo_names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.rig.servos)

    @property
    def frame_period(self) -> float:
        return 1.0 / self.rig.frame_rate

    def _event(self, where: str, message: str) -> None:
        self.events.append((self.clock(), where, message))
        self.log(f"{where}: {message}")

    def configure(self) -> None:
        """Open every bus and configure its servos (raises InputError naming a missing/wrong servo)."""
        try:
            for name, spec in self.rig.buses.items():
                options = dict(self.bus_options.get(name, {}))
                options.setdefault("log", lambda message, name=name: self._event(name, message))
                if spec.facts.estop_modes:
                    options.setdefault("estop", self.rig.estop)
                bus = open_bus(spec.url, **options)
                self.buses[name] = bus
                setups = [ServoSetup(s.address, s.low, s.high, s.neutral, s.model, s.name)
                          for s in self.rig.servos if s.bus == name]
                bus.configure(setups, self.frame_period)
        except BaseException:
            self.close(ease=False)
            raise

    def activate(self, t: float | None = None) -> None:
        """Torque on at the present positions; the safety stage ramps up from there (soft start)."""
        present = np.full(len(self.rig.servos), np.nan)
        for name, bus in self.buses.items():
            positions = bus.activate()
            for i in self._by_bus[name]:
                present[i] = positions.get(self.rig.servos[i].address, np.nan)
        self.state = self.mapper.start(present, self.clock() if t is None else t)
        self.last_targets = self.state.target.copy()

    def send(self, contractions, t: float | None = None, poll: bool | None = None) -> np.ndarray:
        """One frame: contractions (n_muscles,) or None -> integer raw targets (n_servos,) sent to the buses.

        ``poll``: read the servos' status after the write; None (default) every ``poll_every`` frames.
        A caller that passes False polls with :meth:`poll` when the bytes are out (same thread).
        """
        if self.state is None:
            raise RuntimeError("ServoOutput.send before activate()")
        t = self.clock() if t is None else t
        self.state, targets = self.mapper.step(self.state, contractions, t)
        raw = to_raw_int(targets, self.mapper.low, self.mapper.high)
        self.last_targets = targets
        if self.state.estopped:
            return raw
        if poll is None:
            poll = self.frames % self.poll_every == 0
        self.frames += 1
        def write(name, bus):
            bus.write({self.rig.servos[i].address: int(raw[i]) for i in self._by_bus[name]})
            if poll:
                bus.poll()

        self._on_every_bus(write)
        return raw

    def poll(self) -> None:
        """Read every bus's servo status now (what ``send`` does every ``poll_every`` frames).

        May be called from another thread than :meth:`send` (a write then waits for the poll to finish).
        """
        self._on_every_bus(lambda name, bus: bus.poll())

    def _on_every_bus(self, action) -> None:
        """``action(name, bus)`` on every working bus, holding the wire; a bus whose port fails is left out."""
        with self._wire:
            for name, bus in self.buses.items():
                if name in self.failed_buses:
                    continue
                try:
                    action(name, bus)
                except OSError as error:  # the port went away: report, keep the other buses running
                    self.failed_buses.add(name)
                    self._event(name, f"bus failed ({error}); left out from now on")

    def status(self) -> dict[str, ServoStatus | None]:
        """Servo name -> last known status."""
        out = {}
        for servo in self.rig.servos:
            bus = self.buses.get(servo.bus)
            out[servo.name] = bus.status.get(servo.address) if bus else None
        return out

    def faults(self) -> dict[str, str]:
        """Servo name -> fault text, for servos currently stopped by a fault."""
        out = {}
        for servo in self.rig.servos:
            bus = self.buses.get(servo.bus)
            fault = bus.faults.get(servo.address) if bus else None
            if fault:
                out[servo.name] = fault
        for name in self.failed_buses:
            for i in self._by_bus[name]:
                out[self.rig.servos[i].name] = "bus failed"
        return out

    def recover(self, servo_name: str) -> bool:
        """Try to bring a faulted servo back with its bus's ``recover`` (Dynamixel: reboot + reconfigure + soft
        start; a hobby-servo controller cannot: False)."""
        servo = self.rig.servo(servo_name)
        bus = self.buses[servo.bus]
        ok = bus.recover(servo.address)
        if ok and self.state is not None:
            position = bus.status.get(servo.address)
            i = self.servo_names.index(servo_name)
            if position is not None and position.position is not None:
                target = self.state.target.copy()
                target[i] = np.clip(position.position, self.mapper.low[i], self.mapper.high[i])
                self.state = replace(self.state, target=target)
        return ok

    def estop(self) -> None:
        """E-stop: latch the safety stage and stop every bus now."""
        if self.state is not None:
            self.state = self.mapper.estop(self.state)
        for name, bus in self.buses.items():
            try:
                bus.estop()
            except OSError as error:
                self._event(name, f"E-stop could not reach the bus ({error})")
        self._event("output", "E-stop")

    def deactivate(self) -> None:
        for name, bus in self.buses.items():
            try:
                bus.deactivate()
            except OSError as error:
                self._event(name, f"deactivate failed ({error})")
        self.state = None

    def close(self, ease: bool = True, timeout: float | None = None) -> None:
        """Ease to neutral (unless E-stopped), torque off, release the buses."""
        if ease and self.state is not None and not self.state.estopped:
            self.ease_to_neutral(timeout)
        if self.state is not None:
            self.deactivate()
        for name, bus in list(self.buses.items()):
            try:
                bus.close()
            except (OSError, RuntimeError) as error:
                self._event(name, f"close failed ({error})")
        self.buses.clear()

    def ease_to_neutral(self, timeout: float | None = None) -> None:
        """Move every servo to neutral at the watchdog's easing rate, in real time."""
        self.state = replace(self.state, t_input=-np.inf)
        deadline = self.clock() + (timeout if timeout is not None else self.rig.ease_s + 1.0)
        while self.clock() < deadline:
            self.send(None)
            if np.all(np.abs(self.state.target - self.mapper.neutral) < 0.5):
                time.sleep(2 * self.frame_period)  # let the servos finish the last profile
                break
            time.sleep(self.frame_period)
