"""An in-process CAN transport behind python-can's ``Bus`` interface.

python-can's ``virtual`` interface deep-copies every frame once per receiver (about 30 µs a
copy in CPython), which is most of the cost of a lockstep cycle when the gateway and the
emulated drive share a process. :class:`InProcessChannel` connects buses that hand every
receiver the same freshly built, timestamped :class:`can.Message` (receivers must treat
frames as read-only, as python-can's listeners and python-canopen do). There is no global
registry: a channel object connects the buses made from it.

    channel = InProcessChannel("hil-sim")
    gateway_bus = channel.bus(receive_own_messages=True)
    drive_bus = channel.bus()
"""

from __future__ import annotations

import queue
import threading
import time

import can


class InProcessChannel:
    """A shared medium; :meth:`bus` makes a python-can bus attached to it."""

    def __init__(self, name: str = "inprocess") -> None:
        self.name = name
        self._buses: tuple[InProcessBus, ...] = ()
        self._lock = threading.Lock()

    def bus(self, receive_own_messages: bool = False) -> InProcessBus:
        """A new bus on this channel."""
        b = InProcessBus(self, receive_own_messages)
        with self._lock:
            self._buses = (*self._buses, b)
        return b

    def _detach(self, b: InProcessBus) -> None:
        with self._lock:
            self._buses = tuple(x for x in self._buses if x is not b)

    def _deliver(self, sender: InProcessBus, msg: can.Message) -> None:
        for b in self._buses:  # a tuple: safe to iterate while buses attach or detach
            if b is not sender or sender.receive_own_messages:
                b._queue.put(msg)


class InProcessBus(can.BusABC):
    """One node's access to an :class:`InProcessChannel` (python-can ``BusABC``)."""

    def __init__(self, medium: InProcessChannel, receive_own_messages: bool = False) -> None:
        self._medium = medium
        self.receive_own_messages = receive_own_messages
        self._queue: queue.SimpleQueue[can.Message] = queue.SimpleQueue()
        self._open = True
        super().__init__(channel=medium.name)
        self.channel_info = f"in-process channel {medium.name!r}"

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if not self._open:
            raise can.CanOperationError("the in-process bus is shut down")
        frame = can.Message(
            timestamp=time.time(), arbitration_id=msg.arbitration_id,
            is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
            is_error_frame=msg.is_error_frame, dlc=msg.dlc, data=msg.data,
            channel=self._medium.name, is_fd=msg.is_fd, check=False,
        )
        self._medium._deliver(self, frame)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        try:
            return self._queue.get(timeout=timeout), False
        except queue.Empty:
            return None, False

    def shutdown(self) -> None:
        if self._open:
            self._open = False
            self._medium._detach(self)
        super().shutdown()


#: The transports `hil-gateway sim` offers between the gateway and the emulated drive:
#: this module's in-process channel, or python-can's virtual interface.
TRANSPORTS: tuple[str, ...] = ("inprocess", "virtual")
