"""An in-process CAN transport behind python-can's ``Bus`` interface.

python-can's ``virtual`` interface deep-copies every frame once per receiver (about 30 µs a
copy in CPython), which is most of the cost of a lockstep cycle when the gateway and the
emulated drive share a process. :class:`InProcessChannel` connects buses that hand every
receiver the same freshly built, timestamped :class:`can.Message` (receivers must treat
frames as read-only, as python-can's listeners and python-canopen do). There is no global
registry: a channel object connects the buses made from it.

    channel = InProcessChannel("hil-sim")
    gateway_bus = channel.bus(receive_own_messages=True)
    drive_bus = channel.bus(in_sender_thread=True)
    drive_bus.set_receiver(handle)   # handle(msg) runs in the thread of each send

A bus queues what it receives for ``recv`` (a receive thread, python-can's notifier). One
bus of a channel may instead deliver **in the sender's thread** (``in_sender_thread``):
once its owner has set a receiver, each frame is handed to it in the thread that sent it,
inside that ``send``, with one exception: a thread that took a frame from a queued bus of
the channel (a receive thread) is handling that frame until it asks for the next, and the
frames it sends meanwhile are handed on when it asks (first thing in its ``recv``), or
earlier when another thread sends. So the frames a receive thread sends in answer to one
frame all go on the channel before the receiver reacts to any of them, as with a receiver
in a thread of its own, which gets the interpreter only once the receive thread waits:
the gateway's RPDOs and SYNC of a cycle, then the drive's answers. Frames reach the
receiver one at a time and in the channel's order: a per-bus lock serialises the threads
that hand frames on, and a frame sent from inside the receiver (or by another thread
meanwhile) waits its turn, handed on by the thread already delivering. The channel orders
every frame for all its buses at once, so every receiver sees the same sequence. No lock is
held while a receiver waits for anything but that per-bus lock; a receiver must not wait
for a frame to be handled by another thread. An exception raised by the receiver is logged
and does not reach the sender. Without a receiver (before it is set, after it is removed)
the bus queues like any other, and setting a receiver hands it what was queued first. Used
by `hil-gateway sim` for the emulated drive: a lockstep cycle then needs no thread
hand-off.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Callable

import can

log = logging.getLogger(__name__)


class InProcessChannel:
    """A shared medium; :meth:`bus` makes a python-can bus attached to it."""

    def __init__(self, name: str = "inprocess") -> None:
        self.name = name
        self._buses: tuple[InProcessBus, ...] = ()
        #: held only while a frame is put in every receiver's queue (never while waiting):
        #: all buses see the frames in one order
        self._lock = threading.Lock()
        self._direct: InProcessBus | None = None  # the bus that delivers in the sender's thread
        #: per thread: ``handling`` is true while it handles a frame taken from a queued bus
        self._local = threading.local()

    def bus(self, receive_own_messages: bool = False, in_sender_thread: bool = False
            ) -> InProcessBus:
        """A new bus on this channel; ``in_sender_thread``: it delivers to the receiver
        its owner sets (:meth:`InProcessBus.set_receiver`) in the sender's thread (module
        docstring; one such bus per channel)."""
        with self._lock:
            if in_sender_thread and self._direct is not None:
                raise ValueError(f"in-process channel {self.name!r} already has a bus that "
                                 "delivers in the sender's thread")
            b = InProcessBus(self, receive_own_messages, in_sender_thread)
            self._buses = (*self._buses, b)
            if in_sender_thread:
                self._direct = b
        return b

    def _detach(self, b: InProcessBus) -> None:
        with self._lock:
            self._buses = tuple(x for x in self._buses if x is not b)
            if b is self._direct:
                self._direct = None

    def _deliver(self, sender: InProcessBus, msg: can.Message) -> None:
        direct = None
        with self._lock:
            for b in self._buses:
                if b is not sender or sender.receive_own_messages:
                    if b._receiver is None:
                        b._queue.put(msg)
                    else:
                        b._pending.append(msg)
                        direct = b
        if direct is not None and not getattr(self._local, "handling", False):
            direct._hand_on()

    def _handled(self) -> None:
        """The calling thread asks a queued bus for its next frame: the one it took before
        is handled, and the frames it sent meanwhile are handed on now."""
        self._local.handling = False
        direct = self._direct
        if direct is not None and direct._pending:
            direct._hand_on()


class InProcessBus(can.BusABC):
    """One node's access to an :class:`InProcessChannel` (python-can ``BusABC``)."""

    def __init__(self, medium: InProcessChannel, receive_own_messages: bool = False,
                 in_sender_thread: bool = False) -> None:
        self._medium = medium
        self.receive_own_messages = receive_own_messages
        #: frames go to the receiver set with :meth:`set_receiver`, in the sender's thread
        self.in_sender_thread = in_sender_thread
        self._queue: queue.SimpleQueue[can.Message] = queue.SimpleQueue()
        self._receiver: Callable[[can.Message], None] | None = None
        self._pending: deque[can.Message] = deque()  # ordered, not yet handed on
        self._rx_lock = threading.RLock()  # one frame at a time to the receiver
        self._handing_on = 0  # the thread handing frames on now (0: none)
        self._open = True
        super().__init__(channel=medium.name)
        self.channel_info = f"in-process channel {medium.name!r}"

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if not self._open:
            raise can.CanOperationError("the in-process bus is shut down")
        self._medium._deliver(self, _frame(msg, self._medium.name))

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """:meth:`can.BusABC.recv`; without filters (python-can's notifier, the gateway)
        the frame as it comes, without the generic loop's clock and level-9 log call."""
        if self._filters is not None or _RECV_LOG.isEnabledFor(self.RECV_LOGGING_LEVEL):
            return super().recv(timeout)
        return self._recv_internal(timeout)[0]

    def set_receiver(self, receiver: Callable[[can.Message], None] | None) -> None:
        """On a bus made with ``in_sender_thread``: hand every frame to ``receiver`` in the
        thread that sent it (what was queued first, in order); None: queue them again for
        :meth:`recv`. Returns once no frame is being handed to the previous receiver (when
        called from another thread than the receiver's)."""
        if not self.in_sender_thread:
            raise ValueError("this in-process bus queues its frames (in_sender_thread=False)")
        medium = self._medium
        with self._rx_lock, medium._lock:
            if receiver is not None and self._receiver is None:
                backlog = []
                while True:
                    try:
                        backlog.append(self._queue.get_nowait())
                    except queue.Empty:
                        break
                self._pending.extendleft(reversed(backlog))
            elif receiver is None:
                while self._pending:
                    self._queue.put(self._pending.popleft())
            self._receiver = receiver
        if receiver is not None:
            self._hand_on()

    def _hand_on(self) -> None:
        """Hand the pending frames to the receiver, one at a time, in order (in the calling
        thread; a frame sent from inside the receiver is handed on after it returns)."""
        me = threading.get_ident()
        if self._handing_on == me:
            return  # this thread is handing on already: the frame is next in its turn
        pending = self._pending
        with self._rx_lock:
            self._handing_on = me
            try:
                while pending:
                    receiver = self._receiver
                    if receiver is None:  # removed meanwhile: the frames were queued
                        break
                    msg = pending.popleft()
                    try:
                        receiver(msg)
                    except Exception:  # the sender is not the receiver: never its error
                        log.exception("in-process channel %r: the receiver failed on frame "
                                      "0x%X %s", self._medium.name, msg.arbitration_id,
                                      bytes(msg.data).hex())
            finally:
                self._handing_on = 0

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.in_sender_thread:
            try:
                return self._queue.get(timeout=timeout), False
            except queue.Empty:
                return None, False
        medium = self._medium
        medium._handled()
        try:
            msg = self._queue.get(timeout=timeout)
        except queue.Empty:
            return None, False
        medium._local.handling = True
        return msg, False

    def shutdown(self) -> None:
        if self._open:
            self._open = False
            self._medium._detach(self)
        super().shutdown()


_RECV_LOG = logging.getLogger("can.bus")  # where can.BusABC.recv logs each frame
_new_message = object.__new__


def _frame(msg: can.Message, channel: str) -> can.Message:
    """A new frame as it arrives: what ``can.Message(timestamp=time.time(), arbitration_id=
    msg.arbitration_id, is_extended_id=msg.is_extended_id, is_remote_frame=
    msg.is_remote_frame, is_error_frame=msg.is_error_frame, dlc=msg.dlc, data=msg.data,
    channel=channel, is_fd=msg.is_fd)`` makes, attribute by attribute, without its keyword
    handling (a third of a send; tests/test_transport.py compares the two)."""
    frame = _new_message(can.Message)
    frame.timestamp = time.time()
    frame.arbitration_id = msg.arbitration_id
    frame.is_extended_id = msg.is_extended_id
    frame.is_remote_frame = remote = msg.is_remote_frame
    frame.is_error_frame = msg.is_error_frame
    frame.channel = channel
    frame.is_fd = msg.is_fd
    frame.is_rx = True
    frame.bitrate_switch = False
    frame.error_state_indicator = False
    data = msg.data
    if data is None or remote:
        data = bytearray()
    elif not isinstance(data, bytearray):
        data = bytearray(data)
    frame.data = data
    dlc = msg.dlc
    frame.dlc = len(data) if dlc is None else dlc
    return frame


#: The transports `hil-gateway sim` offers between the gateway and the emulated drive:
#: this module's in-process channel, or python-can's virtual interface.
TRANSPORTS: tuple[str, ...] = ("inprocess", "virtual")
