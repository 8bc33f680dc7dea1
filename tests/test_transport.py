"""The in-process channel (gateway/transport.py): queued buses, and the bus that delivers in
the sender's thread (`hil-gateway sim`'s emulated drive): order, one frame at a time across
threads, exceptions kept from the sender, the queue before and after a receiver, shutdown."""

from __future__ import annotations

import logging
import threading

import can
import canopen
import pytest

from gateway.transport import InProcessChannel, _frame
from plant.device import DriveDevice


def _msg(can_id: int, *data: int) -> can.Message:
    return can.Message(arbitration_id=can_id, data=bytes(data), is_extended_id=False)


def _drain(bus: can.BusABC) -> list[tuple[int, bytes]]:
    out = []
    while (m := bus.recv(0)) is not None:
        out.append((m.arbitration_id, bytes(m.data)))
    return out


def test_queued_buses_hand_every_receiver_the_frame():
    ch = InProcessChannel("t")
    a, b = ch.bus(receive_own_messages=True), ch.bus()
    a.send(_msg(0x80, 1))
    b.send(_msg(0x181, 2))
    assert _drain(a) == [(0x80, b"\x01"), (0x181, b"\x02")]
    assert _drain(b) == [(0x80, b"\x01")]  # not its own
    assert not a.in_sender_thread and not b.in_sender_thread
    with pytest.raises(ValueError):
        b.set_receiver(lambda m: None)
    a.shutdown()
    b.shutdown()


@pytest.mark.parametrize("msg", [
    can.Message(arbitration_id=0x181, data=[1, 2, 3], is_extended_id=False),
    can.Message(arbitration_id=0x1ABCDEF, data=bytearray(b"\x01\x02"), dlc=5),
    can.Message(arbitration_id=0x80, data=None, is_extended_id=False),
    can.Message(arbitration_id=0x701, is_remote_frame=True, dlc=1, data=b"\x05"),
    can.Message(is_error_frame=True, data=b"\x00\x01", channel="can3", is_rx=False),
    can.Message(arbitration_id=0x123, data=bytes(12), is_fd=True, bitrate_switch=True,
                error_state_indicator=True),
], ids=["list", "bytearray-ext-dlc", "no-data", "remote", "error", "fd"])
def test_a_frame_is_what_the_message_constructor_makes(msg):
    """The channel's frames are built attribute by attribute: the same as python-can's
    constructor with the arguments the channel always gave it."""
    got = _frame(msg, "hil-sim")
    want = can.Message(
        timestamp=got.timestamp, arbitration_id=msg.arbitration_id,
        is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
        is_error_frame=msg.is_error_frame, dlc=msg.dlc, data=msg.data, channel="hil-sim",
        is_fd=msg.is_fd, check=False)
    for name in can.Message.__slots__:
        if not name.startswith("__"):
            assert getattr(got, name) == getattr(want, name), name
            assert type(getattr(got, name)) is type(getattr(want, name)), name
    assert (got.data is msg.data) == (want.data is msg.data)  # shared as the constructor does


def test_recv_honours_filters_and_timeouts():
    ch = InProcessChannel("t")
    a, b = ch.bus(), ch.bus()
    b.set_filters([{"can_id": 0x181, "can_mask": 0x7FF}])
    assert b.recv(0) is None and b.recv(0.01) is None
    a.send(_msg(0x201))
    a.send(_msg(0x181, 7))
    m = b.recv(0.5)
    assert (m.arbitration_id, bytes(m.data)) == (0x181, b"\x07")
    a.send(_msg(0x201))
    assert b.recv(0) is None  # filtered out
    a.shutdown()
    b.shutdown()


def test_the_receiver_runs_in_the_senders_thread_before_send_returns():
    ch = InProcessChannel("t")
    gw, dev = ch.bus(receive_own_messages=True), ch.bus(in_sender_thread=True)
    seen = []
    dev.set_receiver(lambda m: seen.append((threading.get_ident(), m.arbitration_id)))
    gw.send(_msg(0x80))
    assert seen == [(threading.get_ident(), 0x80)]  # already handled, in this thread

    def other():
        gw.send(_msg(0x201))
        seen.append(("returned", None))

    t = threading.Thread(target=other)
    t.start()
    t.join()
    assert seen[1] == (t.ident, 0x201) and seen[2] == ("returned", None)
    assert dev.recv(0) is None  # nothing queued while a receiver takes the frames
    assert _drain(gw) == [(0x80, b""), (0x201, b"")]
    gw.shutdown()
    dev.shutdown()


def test_frames_sent_by_the_receiver_keep_the_channels_order():
    """The drive answers a SYNC with its TPDOs from inside the receiver: every other bus
    gets the SYNC first; a frame the receiver causes for itself waits its turn (no
    re-entry), and it sees the frames in the channel's order."""
    ch = InProcessChannel("t")
    gw = ch.bus(receive_own_messages=True)
    dev = ch.bus(in_sender_thread=True, receive_own_messages=True)
    depth, handled = [0], []

    def receive(m: can.Message) -> None:
        depth[0] += 1
        assert depth[0] == 1, "the receiver was entered again"
        handled.append(m.arbitration_id)
        if m.arbitration_id == 0x80:
            dev.send(_msg(0x181))
            dev.send(_msg(0x281))
            assert handled[-1] == 0x80  # its own frames come after this one returns
        depth[0] -= 1

    dev.set_receiver(receive)
    gw.send(_msg(0x80))
    gw.send(_msg(0x201))
    assert handled == [0x80, 0x181, 0x281, 0x201]
    assert [i for i, _ in _drain(gw)] == handled
    with pytest.raises(ValueError):
        ch.bus(in_sender_thread=True)  # one per channel
    gw.shutdown()
    dev.shutdown()


def test_a_receive_threads_frames_are_handed_on_when_it_asks_for_the_next():
    """The gateway answers a TPDO with RPDOs and the next SYNC from its receive thread: the
    drive handles them (in that thread) only when it asks for its next frame, so its
    answers (an EMCY to an RPDO, the SYNC's TPDOs) come after all of them, as with a drive
    in a thread of its own; another thread's send hands them on earlier, in order."""
    ch = InProcessChannel("t")
    gw = ch.bus(receive_own_messages=True)
    dev = ch.bus(in_sender_thread=True)
    handled = []

    def receive(m: can.Message) -> None:
        handled.append((threading.get_ident(), m.arbitration_id))
        if m.arbitration_id == 0x301:
            dev.send(_msg(0x81))  # the drive objects to this RPDO at once
        elif m.arbitration_id == 0x80:
            dev.send(_msg(0x181))

    dev.set_receiver(receive)
    order = []

    def receive_thread() -> None:
        dev.send(_msg(0x181))  # a TPDO for the gateway
        assert gw.recv(1).arbitration_id == 0x181  # taken: handling it now
        for cob_id in (0x201, 0x301, 0x80):
            gw.send(_msg(cob_id))
        order.append(list(handled))  # nothing handed on yet
        while (m := gw.recv(0)) is not None:  # asks for the next: handed on first
            order.append(m.arbitration_id)

    t = threading.Thread(target=receive_thread)
    t.start()
    t.join()
    assert order[0] == []
    assert handled == [(t.ident, 0x201), (t.ident, 0x301), (t.ident, 0x80)]
    assert order[1:] == [0x201, 0x301, 0x80, 0x81, 0x181]  # the answers after the frames
    # another thread's send hands the deferred frames on before its own
    handled.clear()
    assert gw.recv(0) is None
    dev.send(_msg(0x182))
    assert gw.recv(1).arbitration_id == 0x182  # the main thread handles this one
    gw.send(_msg(0x202))
    assert handled == []

    def other() -> None:
        gw.send(_msg(0x203))

    o = threading.Thread(target=other)
    o.start()
    o.join()
    assert handled == [(o.ident, 0x202), (o.ident, 0x203)]
    assert gw.recv(0).arbitration_id == 0x202  # and the main thread's recv is still fine
    gw.shutdown()
    dev.shutdown()


def test_senders_in_many_threads_are_handed_on_one_at_a_time_in_one_order():
    ch = InProcessChannel("t")
    gw = ch.bus(receive_own_messages=True)
    dev = ch.bus(in_sender_thread=True)
    inside, overlaps, handled = [0], [], []
    lock = threading.Lock()

    def receive(m: can.Message) -> None:
        with lock:
            inside[0] += 1
            if inside[0] > 1:
                overlaps.append(m)
        handled.append((m.arbitration_id, bytes(m.data)))
        for _ in range(50):  # give the other senders a chance to come in
            pass
        with lock:
            inside[0] -= 1

    dev.set_receiver(receive)
    start = threading.Barrier(4)

    def sender(n: int) -> None:
        start.wait()
        for i in range(300):
            gw.send(_msg(0x200 + n, i >> 8, i & 0xFF))

    threads = [threading.Thread(target=sender, args=(n,)) for n in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not overlaps
    assert len(handled) == 1200
    for n in range(4):  # each sender's frames in the order it sent them
        mine = [int.from_bytes(d, "big") for i, d in handled if i == 0x200 + n]
        assert mine == list(range(300))
    assert _drain(gw) == handled  # the queued bus saw the same order
    gw.shutdown()
    dev.shutdown()


def test_a_receiver_that_raises_is_logged_and_the_sender_goes_on(caplog):
    ch = InProcessChannel("t")
    gw, dev = ch.bus(receive_own_messages=True), ch.bus(in_sender_thread=True)
    handled = []

    def receive(m: can.Message) -> None:
        if m.arbitration_id == 0x666:
            raise RuntimeError("a bug in the receiver")
        handled.append(m.arbitration_id)

    dev.set_receiver(receive)
    with caplog.at_level(logging.ERROR, logger="gateway.transport"):
        gw.send(_msg(0x666, 1, 2))
        gw.send(_msg(0x80))
    assert handled == [0x80]
    assert "receiver failed on frame 0x666 0102" in caplog.text
    assert "a bug in the receiver" in caplog.text
    gw.shutdown()
    dev.shutdown()


def test_without_a_receiver_the_bus_queues_and_the_receiver_gets_the_backlog_first():
    ch = InProcessChannel("t")
    gw, dev = ch.bus(), ch.bus(in_sender_thread=True)
    gw.send(_msg(0x701, 0))
    gw.send(_msg(0x80))
    handled = []
    dev.set_receiver(lambda m: handled.append(m.arbitration_id))
    assert handled == [0x701, 0x80]
    gw.send(_msg(0x201))
    assert handled == [0x701, 0x80, 0x201]
    dev.set_receiver(None)
    gw.send(_msg(0x80, 1))
    assert handled == [0x701, 0x80, 0x201]
    assert _drain(dev) == [(0x80, b"\x01")]  # recv works again
    dev.shutdown()
    gw.send(_msg(0x80, 2))  # a bus shut down is off the channel
    assert dev.recv(0) is None
    with pytest.raises(can.CanOperationError):
        dev.send(_msg(0x181))
    gw.shutdown()


def test_removing_the_receiver_waits_for_the_frame_in_hand():
    ch = InProcessChannel("t")
    gw, dev = ch.bus(), ch.bus(in_sender_thread=True)
    entered, release, removed = threading.Event(), threading.Event(), threading.Event()
    seen_removed = []

    def receive(m: can.Message) -> None:
        entered.set()
        release.wait()
        seen_removed.append(removed.is_set())

    dev.set_receiver(receive)
    sender = threading.Thread(target=gw.send, args=(_msg(0x80),))
    sender.start()
    entered.wait()

    def remove() -> None:
        dev.set_receiver(None)
        removed.set()

    remover = threading.Thread(target=remove)
    remover.start()
    release.set()
    sender.join()
    remover.join()
    assert seen_removed == [False]  # set_receiver(None) returned after the frame was done
    gw.shutdown()
    dev.shutdown()


def test_the_emulated_drive_on_a_bus_that_delivers_in_the_senders_thread():
    """No receive thread: the drive answers SDO in the thread of the request; a handler
    exception is the drive's internal error (EMCY 0x1000), never the sender's; stopped, it
    is off the delivery and the bus queues again."""
    ch = InProcessChannel("t")
    gw_bus, dev_bus = ch.bus(receive_own_messages=True), ch.bus(in_sender_thread=True)
    other = ch.bus()
    dev = DriveDevice(dev_bus, node_id=3)
    net = canopen.Network(gw_bus)
    net.connect()
    try:
        dev.start()
        assert {t.name for t in dev._threads} == {"hil-plant-timer-3"}
        node = net.add_node(3, canopen.ObjectDictionary())
        answers = []
        real = dev.sdo.on_request
        dev.sdo.on_request = lambda *a: (answers.append(threading.get_ident()), real(*a))
        assert node.sdo.upload(0x1000, 0)  # the device type
        assert answers == [threading.get_ident()]

        def broken(can_id: int, data: bytes) -> None:
            raise RuntimeError("a bug in the drive")

        dev._dispatch = broken
        gw_bus.send(_msg(0x000, 0x01, 3))  # handled (and failed) inside this send
        assert dev.account()["internal_errors"] == 1
    finally:
        dev.stop()
        net.disconnect()
    other.send(_msg(0x000, 0x81, 3))
    assert [i for i, _ in _drain(dev_bus)] == [0x000]  # queued: nobody took it
    dev_bus.shutdown()
    other.shutdown()


@pytest.mark.parametrize("in_sender_thread", [True, False])
def test_sim_gives_the_drive_a_receive_thread_only_in_real_time(in_sender_thread):
    """open_emulator: in lockstep (the default) the drive handles frames in the sender's
    thread; in real time (the gateway's SYNC thread keeps a schedule) in a thread of its
    own, as before. Either way the drive answers."""
    from dbc.modes import DriveMode
    from dbc.motor import MotorParams
    from gateway.sim import open_emulator

    bus, label, close = open_emulator("inprocess", 9, MotorParams.paper(), DriveMode.IDEAL,
                                      in_sender_thread=in_sender_thread)
    try:
        assert label.startswith("inprocess:")
        names = {t.name for t in threading.enumerate()}
        assert ("hil-plant-rx-9" in names) is not in_sender_thread
        assert "hil-plant-timer-9" in names
        net = canopen.Network(bus)
        net.connect()
        try:
            node = net.add_node(9, canopen.ObjectDictionary())
            assert int.from_bytes(node.sdo.upload(0x1000, 0), "little") != 0
        finally:
            net.notifier.stop()
    finally:
        close()
