"""Raw pseudo-terminals and a small threaded device loop for byte-exact emulators.

A driver opens the *slave* path exactly as it would open ``/dev/ttyUSB0``; the
emulator reads and writes the *master* fd.  Three details make this reliable:

* the slave is put in raw mode, otherwise ONLCR turns 0x0A into 0x0D 0x0A and
  ECHO sends the request back to the driver;
* we keep our own slave fd open for the life of the emulator: when every slave
  fd is closed, reads on the master fail with EIO, which would kill the loop
  each time a driver closes and reopens the port;
* the master is non-blocking and written through select, because a 28 KB
  sensor frame does not fit in the pty buffer in one go.

A pty moves bytes as fast as the kernel copies them; a real link does not.  Given a
:class:`~lelsonar.acquire.devices.link.Link`, :class:`PtyDevice` paces both directions
at its rate: a request reaches the device only once its last byte would have crossed
the link, and an answer leaves in the link's chunks (a USB frame's worth), each written
when its last byte would have arrived.  The pacing follows the device's own timeline,
not the thread's: a thread that wakes late writes every chunk that is due at once, as
the kernel would have buffered them, so scheduling delays do not add up over a frame.
Without a link (``None``) the pty is unpaced, for tests that want speed.
"""

from __future__ import annotations

import collections
import os
import pty
import select
import threading
import time
import tty
from types import TracebackType
from typing import Self

from lelsonar.acquire.devices.link import Link
from lelsonar.errors import DeviceError


class RawPty:
    """A pty pair with the slave in raw mode.

    Attributes
    ----------
    master_fd : int
        Non-blocking; the emulator's side.
    slave_fd : int
        Kept open so the master never sees EIO (see module docstring).
    path : str
        Device path of the slave, e.g. ``/dev/pts/7``: give it to the driver.
    """

    def __init__(self) -> None:
        self.master_fd, self.slave_fd = pty.openpty()
        try:
            tty.setraw(self.slave_fd)
            os.set_blocking(self.master_fd, False)
            self.path = os.ttyname(self.slave_fd)
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        for fd in (self.master_fd, self.slave_fd):
            try:
                os.close(fd)
            except OSError:
                pass
        self.master_fd = self.slave_fd = -1

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class PtyDevice:
    """Base of an emulated device: one thread serving one raw pty.

    Subclasses implement :meth:`_on_input`, which is called in the device
    thread with every chunk read from the master, and answer by calling
    :meth:`_schedule` with the bytes and the monotonic time at which they are due.
    Scheduled chunks go out in order (a late chunk delays the ones behind it,
    as on a real serial line).

    Parameters
    ----------
    name : str
        Names the thread (``<name>-emulator``) and the errors.
    link : Link, optional
        Pace input and output at this link's rate (see the module docstring); None: unpaced.

    Use as a context manager, or call :meth:`start` and :meth:`stop`.
    """

    #: Bytes read from the master per os.read.
    _READ_SIZE = 65536

    def __init__(self, name: str, link: Link | None = None) -> None:
        self._name = name
        self.link = link
        #: When the line is next free in each direction (monotonic s): the pacing's own clock.
        self._tx_free = 0.0
        self._rx_free = 0.0
        self._rx_queue: collections.deque[tuple[float, bytes]] = collections.deque()
        self._pty: RawPty | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._wake_r = self._wake_w = -1
        self._queue: collections.deque[tuple[float, bytes]] = collections.deque()
        self._queue_lock = threading.Lock()
        self._last_due = 0.0
        self._failure: BaseException | None = None

    # --- lifecycle ---------------------------------------------------------------------
    @property
    def path(self) -> str:
        """Slave device path for a driver to open; only valid once started."""
        if self._pty is None:
            raise DeviceError(f"{self._name} emulator is not started; call start() first")
        return self._pty.path

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> Self:
        """Open the pty and start serving it in a daemon thread."""
        if self._thread is not None:
            raise DeviceError(f"{self._name} emulator already started")
        self._pty = RawPty()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"{self._name}-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread and close every fd; idempotent."""
        if self._thread is not None:
            self._stop.set()
            self._wake()
            self._thread.join(timeout=5.0)
            self._thread = None
        for fd in (self._wake_r, self._wake_w):
            if fd >= 0:
                os.close(fd)
        self._wake_r = self._wake_w = -1
        if self._pty is not None:
            self._pty.close()
            self._pty = None
        if self._failure is not None:
            failure, self._failure = self._failure, None
            raise DeviceError(f"{self._name} emulator thread failed: {failure!r}") from failure

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    # --- for subclasses ----------------------------------------------------------------
    def _on_input(self, data: bytes, now: float) -> None:
        raise NotImplementedError

    def _schedule(self, data: bytes, due: float) -> None:
        """Queue bytes to start out at monotonic time ``due`` (after anything queued before).

        With a link, the bytes cross it at its rate from ``due`` (or from when the line is
        free): each chunk is queued for the time its last byte arrives.
        """
        if not data:
            return
        with self._queue_lock:
            due = max(due, self._last_due)
            if self.link is None:
                self._queue.append((due, data))
                self._last_due = due
            else:
                rate, step = self.link.bytes_per_s, self.link.chunk_bytes
                start = max(due, self._tx_free)
                for lo in range(0, len(data), step):
                    chunk = data[lo : lo + step]
                    self._queue.append((start + (lo + len(chunk)) / rate, chunk))
                self._tx_free = start + len(data) / rate
                self._last_due = self._tx_free
        if threading.current_thread() is not self._thread:
            self._wake()

    def _received(self, data: bytes, now: float) -> None:
        """Bytes read from the master at ``now``: handled when their last byte would have crossed the link."""
        if self.link is None:
            self._on_input(data, now)
            return
        arrival = max(now, self._rx_free) + self.link.seconds(len(data))
        self._rx_free = arrival
        self._rx_queue.append((arrival, data))

    def _wake(self) -> None:
        if self._wake_w >= 0:
            try:
                os.write(self._wake_w, b"x")
            except BlockingIOError:  # the pipe is full: the loop is awake anyway
                pass

    # --- the loop ----------------------------------------------------------------------
    def _run(self) -> None:
        assert self._pty is not None
        master = self._pty.master_fd
        pending = bytearray()  # bytes due now but not yet accepted by the pty
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                rx = self._rx_queue
                while rx and rx[0][0] <= now:
                    arrival, data = rx.popleft()
                    self._on_input(data, arrival)
                with self._queue_lock:
                    while self._queue and self._queue[0][0] <= now:
                        pending += self._queue.popleft()[1]
                    next_due = self._queue[0][0] if self._queue else None
                if rx and (next_due is None or rx[0][0] < next_due):
                    next_due = rx[0][0]
                if pending:
                    self._write_some(master, pending)  # at once: a select first would only add latency
                timeout = None if next_due is None else max(0.0, next_due - now)
                readable, writable, _ = select.select([master, self._wake_r], [master] if pending else [], [], timeout)
                if self._wake_r in readable:
                    try:
                        os.read(self._wake_r, 4096)
                    except BlockingIOError:
                        pass
                if master in readable:
                    try:
                        data = os.read(master, self._READ_SIZE)
                    except BlockingIOError:
                        data = b""
                    if data:
                        self._received(data, time.monotonic())
                if pending and master in writable:
                    self._write_some(master, pending)
        except BaseException as exc:  # surfaced by stop(); a dead emulator must not pass silently
            self._failure = exc

    @staticmethod
    def _write_some(fd: int, pending: bytearray) -> None:
        """Write what the pty accepts now; keep the rest for the next writable select."""
        try:
            written = os.write(fd, pending)
        except BlockingIOError:
            return
        del pending[:written]
