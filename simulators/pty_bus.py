"""A pseudo-terminal that a simulated device serves from a thread, or from its own process.

The transport only moves bytes: whatever the client writes to the slave side
(``/dev/pts/N``, opened with pyserial or a vendor SDK like any serial port)
is handed to ``handler(data) -> replies``; each reply is written back after
its delay. The device logic lives in the handler, as pure framing + state.
:class:`PtyDevice` is the lifecycle (start, close, context manager) and the
reply fault injection that the device simulators share;
:class:`DeviceProcess` serves a device from a child process; :func:`simulated_device`
and :func:`open_on_pty` are the halves of a ``sim...://`` scheme's opener (the
device, then the real driver's bus on its pseudo-terminal, closing the device
when it closes).
"""

from __future__ import annotations

import os
import random
import select
import subprocess
import threading
import time
import tty
from collections.abc import Callable, Iterable
from typing import TypeVar

Reply = tuple[float, bytes]  # (delay in seconds before sending, bytes)
Bus = TypeVar("Bus")


class PtyBus:
    """Serve a pseudo-terminal from a background thread.

    Parameters
    ----------
    handler : callable
        ``handler(data: bytes) -> iterable of (delay_s, reply_bytes)``;
        called on the serving thread for each chunk the client writes.
    tick : callable, optional
        Called about every ``tick_period`` seconds on the serving thread
        (device clocks: motion, watchdogs, temperature).
    """

    def __init__(self, handler: Callable[[bytes], Iterable[Reply]], tick: Callable[[], None] | None = None,
                 tick_period: float = 0.02):
        self.handler = handler
        self.tick = tick
        self.tick_period = tick_period
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.bytes_in = 0
        self.bytes_out = 0
        self.error: BaseException | None = None
        self.served = threading.Condition()  # notified after each chunk's replies are written and each tick
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name=f"pty-bus {self.path}", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        last_tick = time.monotonic()
        try:
            while not self._stop.is_set():
                ready, _, _ = select.select([self.master], [], [], self.tick_period)
                if ready:
                    try:
                        data = os.read(self.master, 65536)
                    except OSError:  # no client has the slave open: nothing to read yet
                        time.sleep(self.tick_period)
                        continue
                    self.bytes_in += len(data)
                    for delay, reply in self.handler(data):
                        if delay > 0:
                            time.sleep(delay)
                        if reply:
                            self._write(reply)
                now = time.monotonic()
                if self.tick is not None and now - last_tick >= self.tick_period:
                    last_tick = now
                    self.tick()
                with self.served:
                    self.served.notify_all()
        except BaseException as error:  # surfaced through .error and close()
            self.error = error
        finally:
            with self.served:
                self.served.notify_all()

    def wait_until(self, predicate: Callable[[], bool], timeout: float = 5.0) -> bool:
        """Wait until ``predicate()`` is true, re-checked each time the serving thread handled bytes or ticked.

        Returns the last value of ``predicate()`` (False: ``timeout`` seconds passed, or serving stopped).
        For tests: wait for what the device did (counters, state) instead of sleeping a fixed time, which
        a loaded machine can outlast.
        """
        deadline = time.monotonic() + timeout
        with self.served:
            while not predicate():
                left = deadline - time.monotonic()
                if left <= 0 or not self._thread.is_alive():
                    return bool(predicate())
                self.served.wait(min(left, 0.05))
        return True

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            written = os.write(self.master, view)
            self.bytes_out += written
            view = view[written:]

    def close(self) -> None:
        """Stop serving and close both ends; re-raise an error the serving thread hit."""
        self._stop.set()
        self._thread.join(timeout=2.0)
        # bytes the client wrote just before closing (a last torque-off) still reach the device
        try:
            while select.select([self.master], [], [], 0)[0]:
                data = os.read(self.master, 65536)
                if not data:
                    break
                self.handler(data)
        except OSError:
            pass
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass
        if self.error is not None:
            raise RuntimeError(f"simulated bus {self.path} failed") from self.error

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class PtyDevice:
    """Base of a simulated device served on a :class:`PtyBus`.

    A subclass defines ``handle(data) -> list[Reply]`` and, when
    ``tick_period`` is not None, ``tick()`` (called about every
    ``tick_period`` seconds on the serving thread). For reply fault
    injection it sets ``random`` (a ``random.Random``), ``drop_rate`` and
    ``corrupt_rate``.
    """

    tick_period: float | None = None
    pty: PtyBus | None = None
    random: random.Random
    drop_rate: float
    corrupt_rate: float

    def handle(self, data: bytes) -> Iterable[Reply]:
        raise NotImplementedError

    def tick(self) -> None:
        raise NotImplementedError

    def start(self) -> str:
        """Serve on a new pseudo-terminal; returns its path."""
        if self.tick_period is None:
            self.pty = PtyBus(self.handle)
        else:
            self.pty = PtyBus(self.handle, tick=self.tick, tick_period=self.tick_period)
        return self.pty.path

    def close(self) -> None:
        if self.pty is not None:
            self.pty.close()
            self.pty = None

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc):
        self.close()

    def wait_until(self, predicate: Callable[[], bool], timeout: float = 5.0) -> bool:
        """:meth:`PtyBus.wait_until` on the running simulator (the device state after the bytes sent so far)."""
        if self.pty is None:
            raise RuntimeError("simulator not started")
        return self.pty.wait_until(predicate, timeout)

    def inject_fault(self, data: bytes) -> bytes | None:
        """``data`` dropped (None) with probability ``drop_rate``, else one bit flipped with ``corrupt_rate``.

        A corrupted reply always differs from ``data`` (exactly one bit is flipped).
        """
        if self.drop_rate and self.random.random() < self.drop_rate:
            return None
        if self.corrupt_rate and self.random.random() < self.corrupt_rate:
            data = bytearray(data)
            data[self.random.randrange(len(data))] ^= 1 << self.random.randrange(8)
        return bytes(data)


def serve_from_stdin() -> None:
    """Child process of :class:`DeviceProcess`: a pickled ``(factory, options)`` on stdin, the pseudo-terminal's
    path written to stdout, then serve until stdin closes (the parent stopped it, or the parent is gone)."""
    import pickle
    import sys

    factory, options = pickle.load(sys.stdin.buffer)
    device = factory(**options)
    try:
        print(device.start(), flush=True)
        sys.stdin.buffer.read()  # returns at EOF
    finally:
        device.close()


class DeviceProcess:
    """A simulated device (a :class:`PtyDevice` class and its options) served from its own process.

    Like real hardware, it then takes no CPU time or interpreter lock from the process that drives it:
    a simulator thread in the pipeline's process competes with the pipeline for Python's GIL. Same
    lifecycle as :class:`PtyDevice` (:meth:`start` returns the pseudo-terminal's path, :meth:`close`);
    the device's state lives in the child, so tests that inspect it use an in-process simulator. The
    child is a fresh interpreter (not a fork, and not ``multiprocessing``, which would re-run the
    parent's main script); it ends when its stdin closes, also when the parent dies.

    Parameters
    ----------
    factory : type
        A :class:`PtyDevice` subclass (picklable).
    options : dict
        Its constructor's keyword arguments.
    """

    def __init__(self, factory, options: dict):
        self.factory, self.options = factory, dict(options)
        self._process = None

    def start(self, timeout: float = 60.0) -> str:
        import pickle
        import sys

        code = "from livebridge.simulators.pty_bus import serve_from_stdin; serve_from_stdin()"
        # a session of its own: Ctrl-C in a terminal signals the whole foreground process group, and the
        # device must outlive that signal while its driver eases the servos to neutral and turns torque off
        self._process = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                         start_new_session=True)
        self._process.stdin.write(pickle.dumps((self.factory, self.options)))
        self._process.stdin.flush()
        ready, _, _ = select.select([self._process.stdout], [], [], timeout)
        path = self._process.stdout.readline().decode().strip() if ready else ""
        if not path:
            self.close()
            raise RuntimeError(f"the simulated {self.factory.__name__} did not start within {timeout} s")
        return path

    @property
    def pid(self) -> int | None:
        """The serving process's id while it runs (None before :meth:`start` and after :meth:`close`)."""
        return None if self._process is None else self._process.pid

    def close(self) -> None:
        if self._process is None:
            return
        try:
            self._process.stdin.close()
        except OSError:
            pass
        try:
            self._process.wait(timeout=5.0)
        except subprocess.TimeoutExpired:  # it would not stop, so it is killed
            self._process.kill()
            self._process.wait(timeout=5.0)
        self._process.stdout.close()
        self._process = None

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc):
        self.close()


def simulated_device(factory, options: dict, own_process: bool):
    """The simulated device ``factory(**options)``, or with ``own_process`` the same device served from its
    own process (:class:`DeviceProcess`), as hardware would be: no simulator thread then competes with the
    driving process for the CPU and the GIL. Either has ``start() -> path`` and ``close()``.
    """
    device = factory(**options)  # built here either way: bad options are reported at once, in this process
    return DeviceProcess(factory, options) if own_process else device


def open_on_pty(device, open_bus: Callable[[str], Bus]) -> Bus:
    """Start ``device`` on a pseudo-terminal and return ``open_bus(path)``; the device is closed if that fails.

    ``open_bus`` hands the device to the bus it opens (the driver's ``companion``), so closing the bus
    closes the device.
    """
    path = device.start()
    try:
        return open_bus(path)
    except BaseException:
        device.close()
        raise
