"""A small CiA 402 drive written for the tests from CiA 301/402 and the paper's model (1) alone:
nothing of ``plant/`` or of the emulator's contract (other objects, names, layout, scalings,
COB-IDs; no SYNC-counter echo; TPDOs sent in reversed order; node 127 works).

* CiA 301: boot-up and heartbeat (0x1017), NMT start/stop/pre-operational/reset
  communication/reset node, SDO by python-canopen's ``LocalNode`` on its own object
  dictionary (an EDS written below), synchronous PDOs with fixed mappings (the master reads
  them back: the profile says ``remap = false``). No 0x1007, 0x1016, 0x1019.
* CiA 402: the power state machine on 0x6040/0x6041 (enough for enable/disable/fault reset).
* The plant: an ideal current source whose (d, q) setpoints the drive turns from the frame
  angle at the frame speed it receives, feeding the induction motor of model (1)
  (integrated with RK4, 20 steps per period), a dynamometer applying the load torque it
  receives; it reports the phase currents, the average applied voltages
  (ψ_s increment / T + R_s·mean current), the DC link, and the motor's truth.

:func:`write_files` writes the drive's EDS, DBC and drive profile into a directory.
"""

from __future__ import annotations

import cmath
import math
import struct
import threading
from pathlib import Path

import can
import canopen

#: The paper's motor (section 6), written here again on purpose.
J, R_S, R_R, L_S, L_R, M = 0.0075, 5.3, 3.3, 0.365, 0.375, 0.34
ALPHA, MU, SIGMA = R_R / L_R, M / (J * L_R), L_S - M * M / L_R

#: Scalings of this drive (its own units per bit).
ANGLE, SPEED, CURRENT, VOLTAGE = 2 * math.pi / 65536, 1 / 16, 0.002, 0.05
FLUX, TORQUE = 0.0002, 0.02

# Object indices (manufacturer area 0x3000..).
O_ANGLE, O_SPEED = 0x3000, 0x3001
O_ID, O_IQ, O_UD, O_UQ, O_LOAD = 0x3010, 0x3011, 0x3012, 0x3013, 0x3014
O_IA, O_IB, O_UA, O_UB, O_UDC = 0x3100, 0x3101, 0x3110, 0x3111, 0x3112
O_W, O_PSA, O_PSB, O_TE = 0x3200, 0x3201, 0x3202, 0x3203

#: (object, name, EDS type, access, struct code, scale)
OBJECTS = [
    (O_ANGLE, "Frame angle", 0x6, "rww", "H", ANGLE), (O_SPEED, "Frame speed", 0x3, "rww",
                                                        "h", SPEED),
    (O_ID, "Current d setpoint", 0x3, "rww", "h", CURRENT),
    (O_IQ, "Current q setpoint", 0x3, "rww", "h", CURRENT),
    (O_UD, "Voltage d setpoint", 0x3, "rww", "h", VOLTAGE),
    (O_UQ, "Voltage q setpoint", 0x3, "rww", "h", VOLTAGE),
    (O_LOAD, "Dynamometer torque", 0x3, "rww", "h", TORQUE),
    (O_IA, "Phase current A", 0x3, "ro", "h", CURRENT),
    (O_IB, "Phase current B", 0x3, "ro", "h", CURRENT),
    (O_UA, "Voltage alpha", 0x3, "ro", "h", VOLTAGE),
    (O_UB, "Voltage beta", 0x3, "ro", "h", VOLTAGE),
    (O_UDC, "DC bus", 0x6, "ro", "H", VOLTAGE),
    (O_W, "Rotor speed", 0x3, "ro", "h", SPEED), (O_PSA, "Rotor flux A", 0x3, "ro", "h", FLUX),
    (O_PSB, "Rotor flux B", 0x3, "ro", "h", FLUX), (O_TE, "Torque", 0x3, "ro", "h", TORQUE),
]
SCALE = {o[0]: o[5] for o in OBJECTS}
CODE = {o[0]: o[4] for o in OBJECTS}
CODE.update({0x6040: "H", 0x6041: "H"})

#: The PDOs: (RPDO?, number, [objects in frame order]) — TPDO1 carries b before a.
RPDOS = [(1, [0x6040, O_ANGLE, O_SPEED]), (2, [O_ID, O_IQ, O_UD, O_UQ]), (3, [O_LOAD])]
TPDOS = [(1, [O_IB, O_IA, 0x6041]), (2, [O_UA, O_UB, O_UDC]), (3, [O_W, O_PSA, O_PSB, O_TE])]
#: DBC signal names (the drive's own) for each object, and the gateway's role for each.
SIGNAL = {0x6040: ("Control", "controlword"), 0x6041: ("Status", "statusword"),
          O_ANGLE: ("Angle", "eps_0"), O_SPEED: ("AngSpeed", "w_0"),
          O_ID: ("IdSet", "i_sd_ref"), O_IQ: ("IqSet", "i_sq_ref"), O_UD: ("UdSet", "u_sd_ref"),
          O_UQ: ("UqSet", "u_sq_ref"), O_LOAD: ("Dyno", "T_L"), O_IA: ("Ia", "i_sa"),
          O_IB: ("Ib", "i_sb"), O_UA: ("Ualpha", "u_sa"), O_UB: ("Ubeta", "u_sb"),
          O_UDC: ("Udc", "u_dc"), O_W: ("Speed", "w_m"), O_PSA: ("FluxA", "psi_ra"),
          O_PSB: ("FluxB", "psi_rb"), O_TE: ("Torque", "T_e")}
DEVICE_TYPE = 0x00020192


def eds_text(node: int) -> str:
    """The drive's EDS (CiA 306), with its PDO mappings as defaults."""
    out = ["[FileInfo]", "FileName=foreign.eds", "EDSVersion=4.0", "Description=test drive",
           "", "[DeviceInfo]", "VendorName=Foreign", "ProductName=Test drive",
           f"NrOfRXPDO={len(RPDOS)}", f"NrOfTXPDO={len(TPDOS)}", ""]

    def var(section: str, name: str, dtype: int, access: str, default: str,
            pdo: bool = False) -> None:
        out.extend([f"[{section}]", f"ParameterName={name}", "ObjectType=0x7",
                    f"DataType=0x{dtype:04X}", f"AccessType={access}",
                    f"DefaultValue={default}", f"PDOMapping={int(pdo)}", ""])

    def record(index: int, name: str, subs: list[tuple[str, int, str, str]]) -> None:
        out.extend([f"[{index:04X}]", f"ParameterName={name}", "ObjectType=0x9",
                    f"SubNumber={len(subs)}", ""])
        for k, (sname, dtype, access, default) in enumerate(subs):
            var(f"{index:04X}sub{k}", sname, dtype, access, default)

    var("1000", "Device type", 0x7, "ro", f"0x{DEVICE_TYPE:08X}")
    var("1001", "Error register", 0x5, "ro", "0")
    var("1006", "Communication cycle period", 0x7, "rw", "0")
    var("1017", "Producer heartbeat time", 0x6, "rw", "0")
    for n, objs in RPDOS:
        record(0x1400 + n - 1, f"RPDO{n} communication", [
            ("Highest sub", 0x5, "ro", "5"), ("COB-ID", 0x7, "rw", f"0x{0x100 * (n + 1) + node:X}"),
            ("Transmission type", 0x5, "rw", "1"), ("Inhibit", 0x6, "rw", "0"),
            ("Reserved", 0x5, "rw", "0"), ("Event timer", 0x6, "rw", "0")])
        record(0x1600 + n - 1, f"RPDO{n} mapping", [("Number", 0x5, "rw", str(len(objs)))] + [
            (f"Entry {k}", 0x7, "rw", f"0x{o:04X}0010") for k, o in enumerate(objs, 1)])
    for n, objs in TPDOS:
        record(0x1800 + n - 1, f"TPDO{n} communication", [
            ("Highest sub", 0x5, "ro", "5"),
            ("COB-ID", 0x7, "rw", f"0x{0x100 * n + 0x80 + node:X}"),
            ("Transmission type", 0x5, "rw", "1"), ("Inhibit", 0x6, "rw", "0"),
            ("Reserved", 0x5, "rw", "0"), ("Event timer", 0x6, "rw", "0")])
        record(0x1A00 + n - 1, f"TPDO{n} mapping", [("Number", 0x5, "rw", str(len(objs)))] + [
            (f"Entry {k}", 0x7, "rw", f"0x{o:04X}0010") for k, o in enumerate(objs, 1)])
    var("6040", "Controlword", 0x6, "rww", "0", pdo=True)
    var("6041", "Statusword", 0x6, "ro", "0x0240", pdo=True)
    var("6060", "Modes of operation", 0x2, "rw", "0")
    var("6061", "Modes of operation display", 0x2, "ro", "0")
    for index, name, dtype, access, _, _ in OBJECTS:
        var(f"{index:04X}", name, dtype, access, "0", pdo=True)
    return "\n".join(out) + "\n"


def dbc_text(node: int) -> str:
    """The drive's DBC: its frames at its node, in its own names and scalings."""
    lines = ['VERSION ""', "", "NS_ :", "", "BS_:", "", "BU_: GW DRIVE", ""]
    units = {ANGLE: "rad", SPEED: "rad/s", CURRENT: "A", VOLTAGE: "V", FLUX: "Wb",
             TORQUE: "N.m", 1: ""}
    for rx, pdos in ((True, RPDOS), (False, TPDOS)):
        for n, objs in pdos:
            cob = 0x100 * (n + 1) + node if rx else 0x100 * n + 0x80 + node
            name = f"{'RX' if rx else 'TX'}{n}"
            lines.append(f"BO_ {cob} {name}: {2 * len(objs)} {'GW' if rx else 'DRIVE'}")
            for k, o in enumerate(objs):
                sig = SIGNAL[o][0]
                scale = SCALE.get(o, 1)
                signed = "-" if CODE[o] == "h" else "+"
                lines.append(f' SG_ {sig} : {16 * k}|16@1{signed} ({scale!r},0) [0|0] '
                             f'"{units[scale]}" {"DRIVE" if rx else "GW"}')
            lines.append("")
    return "\n".join(lines) + "\n"


def profile_text(node: int, gateway_node: int = 0x7F) -> str:
    """The drive profile: everything the gateway knows of this drive."""
    signals = "\n".join(f'{role} = "{"RX" if o in {x for _, objs in RPDOS for x in objs} else "TX"}'
                        f'{_pdo_number(o)}.{sig}"' for o, (sig, role) in SIGNAL.items())
    objects = "\n".join(f'"{_message(o)}.{sig}" = "0x{o:04X}.0"'
                         for o, (sig, _) in SIGNAL.items())
    return f"""[drive]
name = "foreign test drive"
eds = "foreign.eds"
dbc = "foreign.dbc"
node = {node}
gateway_node = {gateway_node}
device_type = 0x{DEVICE_TYPE:08X}

[modes]
current = 10
voltage = 11

[pdo]
control = "RX1"
setpoints = "RX2"
load = "RX3"
currents = "TX1"
voltages = "TX2"
truth = "TX3"
remap = false

[signals]
{signals}

[objects]   # the objects each signal maps: the master checks the drive's mappings against them
{objects}

[limits]
current_peak_a = 30.0
dc_link_v = [300.0, 800.0]

[timing]
heartbeat_ms = 50
drive_heartbeat_timeout_ms = 500
rpdo_timeout_ms = 300
"""


def _message(obj: int) -> str:
    """The DBC message (RX1.., TX1..) that maps ``obj``."""
    return ("RX" if any(obj in objs for _, objs in RPDOS) else "TX") + str(_pdo_number(obj))


def _pdo_number(obj: int) -> int:
    for n, objs in RPDOS + TPDOS:
        if obj in objs:
            return n
    raise KeyError(obj)


def write_files(directory: Path, node: int, gateway_node: int = 0x7F) -> Path:
    """foreign.eds, foreign.dbc and foreign.toml in ``directory``; returns the profile."""
    (directory / "foreign.eds").write_text(eds_text(node))
    (directory / "foreign.dbc").write_text(dbc_text(node))
    path = directory / "foreign.toml"
    path.write_text(profile_text(node, gateway_node))
    return path


class _Sender:
    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus

    def send_message(self, can_id: int, data: bytes | bytearray, remote: bool = False) -> None:
        self.bus.send(can.Message(arbitration_id=can_id, data=bytes(data),
                                  is_extended_id=False))


class ForeignDrive:
    """The drive on a python-can bus (threads: receive, heartbeat)."""

    def __init__(self, bus: can.BusABC, node: int, eds: Path) -> None:
        self.bus, self.node = bus, node
        self.od = canopen.import_od(str(eds), node)
        self.local = canopen.LocalNode(node, self.od)
        self.local.sdo.network = _Sender(bus)  # type: ignore[assignment]
        # this drive keeps its own heartbeat (the LocalNode's NMT slave would start one)
        self.local._write_callbacks = [self._on_write]
        self.nmt = "PRE-OPERATIONAL"
        self.state = 0x0240  # switch on disabled
        self.rx: dict[int, dict] = {}  # object → raw value received (latched at SYNC)
        self.active: dict[int, float] = {}
        self.w, self.psi = 0.0, 0j  # motor state
        self.i_end = 0j  # the stator current at the end of the last period
        self.cycles = 0
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._threads = [threading.Thread(target=f, daemon=True)
                         for f in (self._rx_loop, self._hb_loop)]

    # -------------------------------------------------------------- CiA 301
    def start(self) -> None:
        self._send(0x700 + self.node, b"\x00")
        for t in self._threads:
            t.start()

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(2)

    def _send(self, cob: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))

    def _read(self, index: int, sub: int = 0) -> int:
        """An object's present value (written by SDO, or the EDS default)."""
        obj = self.od[index]
        var = obj if isinstance(obj, canopen.objectdictionary.ODVariable) else obj[sub]
        return var.decode_raw(self.local.get_data(index, sub))

    def _hb_loop(self) -> None:
        while not self._stop.wait(0.005):
            period = self._read(0x1017) / 1000.0
            if period <= 0:
                continue
            byte = {"PRE-OPERATIONAL": 0x7F, "OPERATIONAL": 0x05, "STOPPED": 0x04}[self.nmt]
            self._send(0x700 + self.node, bytes([byte]))
            self._stop.wait(period)

    def _rx_loop(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(0.05)
            if msg is None or msg.is_extended_id:
                continue
            with self._lock:
                self._dispatch(msg.arbitration_id, bytes(msg.data))

    def _dispatch(self, cob: int, data: bytes) -> None:
        if cob == 0 and len(data) == 2 and data[1] in (0, self.node):
            cmd = data[0]
            if cmd == 0x01:
                self.nmt = "OPERATIONAL"
            elif cmd == 0x02:
                self.nmt = "STOPPED"
            elif cmd == 0x80:
                self.nmt = "PRE-OPERATIONAL"
            elif cmd in (0x81, 0x82):
                if cmd == 0x81:
                    self.state = 0x0240
                self.nmt = "PRE-OPERATIONAL"
                self._send(0x700 + self.node, b"\x00")
        elif cob == 0x600 + self.node and self.nmt != "STOPPED" and len(data) == 8:
            self.local.sdo.on_request(cob, data, 0.0)
        elif self.nmt == "OPERATIONAL" and cob == 0x80:
            self._sync()
        elif self.nmt == "OPERATIONAL":
            for n, objs in RPDOS:
                if cob == self._read(0x1400 + n - 1, 1) & 0x7FF and len(data) == 2 * len(objs):
                    codes = "<" + "".join(CODE[o] for o in objs)
                    for o, raw in zip(objs, struct.unpack(codes, data), strict=True):
                        self.rx[o] = raw

    # -------------------------------------------------------------- CiA 402
    def _on_write(self, index: int, subindex: int, od, data: bytes) -> None:
        if index == 0x6040:
            self._controlword(struct.unpack("<H", data)[0])

    def _controlword(self, cw: int) -> None:
        """CiA 402 device control (transitions 2–12, 15 of CiA 402-2, enough for a master)."""
        st = self.state
        if st == 0x0208:  # Fault: only a fault reset (rising bit 7) leaves it
            if cw & 0x80:
                st = 0x0240
        elif cw & 0x02 == 0:
            st = 0x0240  # disable voltage → Switch on disabled
        elif cw & 0x0F == 0x06:
            st = 0x0231  # shutdown → Ready to switch on
        elif cw & 0x0F == 0x07 and st in (0x0231, 0x0237):
            st = 0x0233  # switch on → Switched on
        elif cw & 0x0F == 0x0F and st in (0x0231, 0x0233, 0x0237):
            if st != 0x0237:
                self.active = {}  # a new enable starts from zero setpoints
            st = 0x0237  # enable operation → Operation enabled
        self.state = st
        self.local.data_store.setdefault(0x6041, {})[0] = struct.pack("<H", st)

    # -------------------------------------------------------------- the plant
    def _sync(self) -> None:
        T = self._read(0x1006) / 1e6
        if T <= 0:
            return
        self.cycles += 1
        enabled = self.state == 0x0237
        a = self.active
        i_dq = complex(a.get(O_ID, 0.0), a.get(O_IQ, 0.0)) if enabled else 0j
        eps, w0, T_L = a.get(O_ANGLE, 0.0), a.get(O_SPEED, 0.0), a.get(O_LOAD, 0.0)
        n = 20
        h = T / n
        i_sum = 0j
        # the stator flux before the interval, with the current before the setpoint step:
        # the step's σ·Δi is in this period's average voltage, as a real inverter applies it
        psi_s0 = SIGMA * self.i_end + (M / L_R) * self.psi
        for k in range(n):
            t0 = k * h

            def f(t: float, w: float, psi: complex) -> tuple[float, complex]:
                i = i_dq * cmath.exp(1j * (eps + w0 * t))
                dw = MU * (psi.real * i.imag - psi.imag * i.real) - T_L / J
                return dw, (-ALPHA + 1j * w) * psi + ALPHA * M * i

            w, psi = self.w, self.psi
            k1 = f(t0, w, psi)
            k2 = f(t0 + h / 2, w + h / 2 * k1[0], psi + h / 2 * k1[1])
            k3 = f(t0 + h / 2, w + h / 2 * k2[0], psi + h / 2 * k2[1])
            k4 = f(t0 + h, w + h * k3[0], psi + h * k3[1])
            self.w = w + h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
            self.psi = psi + h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
            # mean current over the step (Simpson)
            i_sum += (i_dq * cmath.exp(1j * (eps + w0 * t0)) + 4 * i_dq * cmath.exp(
                1j * (eps + w0 * (t0 + h / 2))) + i_dq * cmath.exp(1j * (eps + w0 * (t0 + h)))) / 6
        i_end = i_dq * cmath.exp(1j * (eps + w0 * T))
        self.i_end = i_end
        psi_s1 = SIGMA * i_end + (M / L_R) * self.psi
        u = (psi_s1 - psi_s0) / T + R_S * i_sum / n
        te = J * MU * (self.psi.real * i_end.imag - self.psi.imag * i_end.real)
        values = {O_IA: i_end.real, O_IB: i_end.imag, O_UA: u.real, O_UB: u.imag, O_UDC: 560.0,
                  O_W: self.w, O_PSA: self.psi.real, O_PSB: self.psi.imag, O_TE: te,
                  0x6041: self.state}
        for n_pdo, objs in reversed(TPDOS):  # reversed order on purpose
            raws = []
            for o in objs:
                if o == 0x6041:
                    raws.append(int(values[o]))
                    continue
                x = round(values[o] / SCALE[o])
                lo, hi = (-32768, 32767) if CODE[o] == "h" else (0, 65535)
                raws.append(min(hi, max(lo, x)))
            cob = self._read(0x1800 + n_pdo - 1, 1) & 0x7FF
            self._send(cob, struct.pack("<" + "".join(CODE[o] for o in objs), *raws))
        # synchronous RPDOs: what arrived in this cycle acts over the next one
        for o, raw in self.rx.items():
            if o == 0x6040:
                self._controlword(raw)
            else:
                self.active[o] = raw * SCALE[o]
        self.rx = {}


def main(argv: list[str] | None = None) -> int:
    """``python tests/foreign_drive.py CHANNEL NODE DIR``: write the drive's files into DIR,
    run the drive on SocketCAN CHANNEL, print one ready line, stop on SIGTERM/SIGINT."""
    import signal
    import sys

    channel, node, directory = (argv if argv is not None else sys.argv[1:])[:3]
    write_files(Path(directory), int(node))
    bus = can.Bus(interface="socketcan", channel=channel)
    drive = ForeignDrive(bus, int(node), Path(directory) / "foreign.eds")
    stop = threading.Event()
    for s in (signal.SIGTERM, signal.SIGINT):
        signal.signal(s, lambda *_: stop.set())
    drive.start()
    print(f"foreign drive: node {node} ready on {channel}", flush=True)
    try:
        while not stop.wait(0.2):
            pass
    finally:
        drive.stop()
        bus.shutdown()
    print(f"foreign drive: stopped after {drive.cycles} cycles", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
