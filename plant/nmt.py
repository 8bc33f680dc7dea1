"""The NMT slave of the emulated drive: its state, the NMT commands and the heartbeats.

CiA 301: after initialisation a node sends its boot-up message (0x700+n, one byte 0x00) and
is PRE-OPERATIONAL. NMT commands (COB-ID 0, [command, node id or 0 for all]): 0x01 start
(OPERATIONAL), 0x02 stop (STOPPED), 0x80 enter PRE-OPERATIONAL, 0x81 reset node, 0x82 reset
communication; each reset ends with a new boot-up. The heartbeat producer (0x1017, ms, 0 =
off) sends 0x700+n with the state (0x7F, 0x05, 0x04); the heartbeat consumer (0x1016 sub 1:
node id << 16 | time in ms) watches another node's heartbeat.

This emulator: the state is a :class:`dbc.cia301.NmtState`; the device's
reactions to the commands are callbacks (the PDO runtime, the resets); the consumer is
armed by the first heartbeat received after (re)configuration and, on its timeout, calls
``heartbeat_lost``. Its time is the device's time base (0x2205, :class:`dbc.timing.TimeBase`):
the wall clock (``time.monotonic()``), as a real device's; or, in lockstep, the simulated
time that SYNCs advance (:meth:`NmtSlave.on_sync`), checked at each SYNC, so that a run
gives the same result on an idle and on a loaded host. Then the wall clock is only a
backstop for a master that stopped altogether: no heartbeat and no SYNC for
:data:`dbc.timing.LOCKSTEP_BACKSTOP_S` (or the consumer time if longer).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from dbc.cia301 import HEARTBEAT_BASE, NmtCommand, NmtState
from dbc.timing import LOCKSTEP_BACKSTOP_S, TimeBase
from plant import od as odm

log = logging.getLogger(__name__)

#: NMT states in which the heartbeat producer runs.
HEARTBEAT_STATES = (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL, NmtState.STOPPED)


_TIME_BASES = {int(b): b for b in TimeBase}

class NmtSlave:
    """NMT state, boot-up, command dispatch, heartbeat producer and consumer.

    ``send(can_id, data)`` puts a frame on the bus; ``wake`` is set whenever a heartbeat
    deadline changes (the device's timer thread waits on it). The callbacks:
    ``start()`` builds the PDO runtime (the state becomes OPERATIONAL after it),
    ``pdos_off()`` drops it (stop, enter PRE-OPERATIONAL), ``reset_node()`` and
    ``reset_communication()`` reset the device (a boot-up follows), ``heartbeat_lost()``
    is the consumer's timeout.
    """

    def __init__(self, node_id: int, values: dict[odm.Key, Any],
                 send: Callable[[int, bytes], None], wake: threading.Event, *,
                 start: Callable[[], None], pdos_off: Callable[[], None],
                 reset_node: Callable[[], None], reset_communication: Callable[[], None],
                 heartbeat_lost: Callable[[], None], own: bool = True) -> None:
        self.node_id = node_id
        self._own = own
        self._values = values
        self._send = send
        self._wake = wake
        self._start = start
        self._pdos_off = pdos_off
        self._reset_node = reset_node
        self._reset_communication = reset_communication
        self._heartbeat_lost = heartbeat_lost
        self.state = NmtState.INITIALISING
        self._hb_period = 0.0
        self._hb_next = 0.0
        self.hb_consumer: tuple[int, float] | None = None  #: (COB-ID, timeout s)
        self._hb_deadline: float | None = None  # wall clock (the backstop in lockstep)
        self._sim = 0.0  # simulated time: SYNC periods seen, s
        self._hb_sim: float | None = None  # simulated time of the last consumed heartbeat

    @property
    def time_base(self) -> TimeBase:
        """0x2205: the consumer's time (wall clock unless the master set SYNC); a twin's
        dictionary is another drive's, whose clock is the wall clock."""
        if not self._own:
            return TimeBase.WALL
        value = self._values.get((odm.TIME_BASE, 0), 0)
        base = _TIME_BASES.get(value)  # every SYNC: a lookup, not an enum call
        return TimeBase(value) if base is None else base

    def _wall_limit(self, timeout: float) -> float:
        return (timeout if self.time_base is TimeBase.WALL
                else max(timeout, LOCKSTEP_BACKSTOP_S))

    def boot(self) -> None:
        """Boot-up message, then PRE-OPERATIONAL (CiA 301)."""
        self._send(HEARTBEAT_BASE + self.node_id, bytes([NmtState.INITIALISING.heartbeat]))
        self.state = NmtState.PRE_OPERATIONAL
        self._hb_next = time.monotonic() + self._hb_period
        self._wake.set()

    def configure_heartbeats(self) -> None:
        """(Re)read 0x1017 and 0x1016 sub 1; the consumer waits for a first heartbeat."""
        self._hb_period = self._values[(0x1017, 0)] / 1000.0
        self._hb_next = time.monotonic() + self._hb_period
        entry = self._values[(0x1016, 1)]
        node, ms = (entry >> 16) & 0xFF, entry & 0xFFFF
        self.hb_consumer = (HEARTBEAT_BASE + node, ms / 1000.0) if node and ms else None
        self._hb_deadline = self._hb_sim = None  # armed by the next heartbeat received
        self._wake.set()

    def on_command(self, data: bytes) -> None:
        """An NMT command frame (COB-ID 0); others' and malformed ones are ignored."""
        if len(data) != 2 or data[1] not in (0, self.node_id):
            return
        cmd = data[0]
        if cmd == NmtCommand.START:
            if self.state is not NmtState.OPERATIONAL:
                self._start()
                self.state = NmtState.OPERATIONAL
        elif cmd == NmtCommand.STOP:
            self.state = NmtState.STOPPED
            self._pdos_off()
        elif cmd == NmtCommand.ENTER_PRE_OPERATIONAL:
            self.state = NmtState.PRE_OPERATIONAL
            self._pdos_off()
        elif cmd == NmtCommand.RESET_NODE:
            log.info("node %d: reset node", self.node_id)
            self._reset_node()
            self.boot()
        elif cmd == NmtCommand.RESET_COMMUNICATION:
            log.info("node %d: reset communication", self.node_id)
            self._reset_communication()
            self.boot()

    def on_heartbeat(self) -> None:
        """The consumed heartbeat arrived: (re)arm its deadlines."""
        assert self.hb_consumer is not None
        self._hb_deadline = time.monotonic() + self._wall_limit(self.hb_consumer[1])
        self._hb_sim = self._sim
        self._wake.set()

    def on_sync(self, period: float) -> None:
        """A SYNC (before the cycle it opens): in SYNC time base the simulated time advances
        by ``period``; the master's heartbeat is lost when none came within the consumer
        time of simulated time, and the SYNC itself keeps the wall-clock backstop off."""
        if self.time_base is TimeBase.WALL:
            return
        self._sim += period
        if self._hb_sim is None or self.hb_consumer is None:
            return
        timeout = self.hb_consumer[1]
        if self._sim - self._hb_sim > timeout * (1 + 1e-9):
            self._hb_deadline = self._hb_sim = None
            self._heartbeat_lost()
        else:
            self._hb_deadline = time.monotonic() + self._wall_limit(timeout)

    def timers(self, now: float) -> float:
        """Heartbeat producer and consumer; returns the time to the next deadline, s."""
        wait = 0.5
        if self._hb_period > 0 and self.state in HEARTBEAT_STATES:
            if now >= self._hb_next:
                self._send(HEARTBEAT_BASE + self.node_id, bytes([self.state.heartbeat]))
                self._hb_next += self._hb_period
                if self._hb_next <= now:
                    self._hb_next = now + self._hb_period
            wait = min(wait, self._hb_next - now)
        if self._hb_deadline is not None:
            if now >= self._hb_deadline:
                self._hb_deadline = None
                self._heartbeat_lost()
            else:
                wait = min(wait, self._hb_deadline - now)
        return wait
