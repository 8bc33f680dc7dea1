"""`hil-gateway check`: commission a drive without power.

Everything a run needs of the drive is checked, with the power stage off throughout: the
CiA 402 state machine is only read (statusword); the RPDOs sent during the SYNC cycles
carry controlword 0x0000 (*disable voltage*, which keeps a drive that is not enabled in a
power-off state) and zero setpoints, so the drive's RPDO deadline monitoring stays
satisfied.

1. the node: NMT reset communication and its boot-up (:meth:`DriveMaster.connect`);
2. device type 0x1000 against the profile, identity 0x1018 (vendor id, product code,
   revision) against the EDS defaults where these are non-zero;
3. every object the profile's PDOs map: in the EDS, PDO-mappable, of the DBC signal's
   size, writable for what the gateway sends (RPDOs) and readable for what the drive sends;
4. the PDO mappings read back from the drive over SDO against the DBC layout (sizes in
   order, COB-ID, enabled) — before configuring with ``remap = false``, after it with
   ``remap = true`` (the written mapping is read back);
5. the roles the current-fed law needs with a current-loop drive
   (:func:`gateway.runner.required_roles`);
6. configured like a run (:meth:`DriveMaster.configure`, NMT OPERATIONAL), ``cycles`` SYNC
   in lockstep at ``period``: per TPDO, the arrival latency after SYNC (median, p99) and
   the cycles in which every TPDO arrived (within the run loop's TPDO timeout, passing
   within a run's missed-cycle tolerance; how many within the period is noted); no EMCY,
   NMT change or lost heartbeat;
7. :meth:`DriveMaster.shutdown`, which must confirm the power stage off.

Exit status: 0 when all checks pass (a run would work), 1 when a check fails — including
*no drive at the node* (the bus opened, nothing answered: a commissioning finding, not bad
input) — and 2 for bad input (profile, EDS, DBC, options, a bus that cannot be opened).
"""

from __future__ import annotations

import argparse
import json
import statistics
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import can

from dbc.bus import add_bus_options, bus_config, open_bus
from dbc.cia301 import SYNC_OVERFLOW
from dbc.cia402 import State
from dbc.modes import DriveMode
from dbc.timing import Sampling, internal_rate
from gateway.atomicfile import write_text_atomic
from gateway.drive_profile import DriveProfile, load_drive_profile
from gateway.errors import UserError
from gateway.master import DeviceRefusedError, DriveMaster
from gateway.outpath import check_writable
from gateway.process_data import ProcessData, process_data

SYNC_ID = 0x080
#: PDO-mappable CANopen data types (CiA 301) → size in bits.
_BITS = {0x1: 1, 0x2: 8, 0x3: 16, 0x4: 32, 0x5: 8, 0x6: 16, 0x7: 32, 0x8: 32, 0x10: 24,
         0x11: 64, 0x12: 40, 0x13: 48, 0x14: 56, 0x15: 64, 0x16: 24, 0x18: 40, 0x19: 48,
         0x1A: 56, 0x1B: 64}
_WRITABLE = ("rw", "wo", "rww", "rwr")
_READABLE = ("ro", "rw", "rwr", "rww", "const")


@dataclass
class Check:
    """One check: its name, whether it passed, what was seen, what to do if it failed."""

    name: str
    ok: bool
    detail: str = ""
    fix: str = ""


@dataclass
class CheckReport:
    drive: str
    node: int
    checks: list[Check] = field(default_factory=list)
    latency: dict[str, dict[str, Any]] = field(default_factory=dict)
    cycles: int = 0
    complete_cycles: int = 0
    power_stage_enabled: bool = False
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return bool(self.checks) and all(c.ok for c in self.checks)

    def add(self, name: str, ok: bool, detail: str = "", fix: str = "") -> bool:
        self.checks.append(Check(name, ok, detail, "" if ok else fix))
        return ok

    def to_json(self) -> dict[str, Any]:
        out = asdict(self)
        out["ok"] = self.ok
        return out

    def text(self) -> str:
        lines = [f"check of {self.drive} at node {self.node}:"]
        for c in self.checks:
            lines.append(f"  [{'PASS' if c.ok else 'FAIL'}] {c.name}: {c.detail}")
            if c.fix:
                lines.append(f"         fix: {c.fix}")
        if self.cycles:
            lines.append(f"  SYNC cycles: {self.cycles}, with every TPDO: {self.complete_cycles}")
            for name, lat in self.latency.items():
                if not lat["received"]:
                    lines.append(f"    {name}: never received")
                    continue
                lines.append(f"    {name}: {lat['received']} received, latency after SYNC "
                             f"median {lat['median_us']:.0f} µs, p99 {lat['p99_us']:.0f} µs")
        for n in self.notes:
            lines.append(f"  note: {n}")
        lines.append("result: " + ("PASS, a run would work" if self.ok else "FAIL"))
        return "\n".join(lines)


# ------------------------------------------------------------------------------ checks


def _identity(report: CheckReport, master: DriveMaster) -> None:
    od = master.node.object_dictionary
    value = master.sdo_read(0x1000, 0)
    want = master.profile.device_type
    report.add("device type 0x1000", want is None or value == want,
               f"0x{int(value):08X}" + ("" if want is None else f", profile 0x{want:08X}"),
               "check --node, or give the drive's own profile with --drive")
    if not master.has(0x1018):
        report.notes.append("the drive's EDS has no identity object 0x1018")
        return
    for sub, what in ((1, "vendor id"), (2, "product code"), (3, "revision")):
        try:
            default = od[0x1018][sub].default
        except (KeyError, TypeError):
            default = None
        if not default:
            continue
        try:
            got = int(master.sdo_read(0x1018, sub))
        except UserError as exc:
            report.add(f"identity 0x1018.{sub} ({what})", False, str(exc),
                       "the drive must answer 0x1018 by SDO")
            continue
        report.add(f"identity 0x1018.{sub} ({what})", got == int(default),
                   f"0x{got:08X}, EDS 0x{int(default):08X}",
                   "this is another drive (or firmware) than the EDS describes: use its EDS")


def _objects(report: CheckReport, master: DriveMaster, pd: ProcessData) -> None:
    remap = master.profile.remap
    for pdo in pd.pdos:
        mapped: list[Any] = []
        if not remap:  # the objects are those the drive maps (read back), in frame order
            try:
                mapped = [v.od for v in master.read_mapping(pdo).map]
            except UserError as exc:
                report.add(f"objects of {pdo.name}", False, str(exc),
                           "the drive must answer its PDO mapping parameters by SDO")
                continue
        for k, ((signal, role), spec) in enumerate(zip(pdo.signals, pdo.codec.signals,
                                                       strict=True)):
            name = f"object of {pdo.name}.{signal} ({role})"
            if remap:
                var = master.object_of(signal, role, pdo.name)
                missing = (f"the EDS ({master.profile.eds}) has no object named {signal!r}",
                           f"name it in the drive profile's [objects] (\"{pdo.name}.{signal}\" "
                           "= \"0xIIII.S\"), or the EDS object like the DBC signal")
            else:
                var = mapped[k] if k < len(mapped) else None
                missing = (f"the drive maps {len(mapped)} objects in {pdo.name}, the DBC "
                           f"has {len(pdo.signals)} signals", "map the PDO as the DBC says")
            if var is not None and not master.has(var.index):
                var = None
                missing = (f"the drive maps an object its EDS ({master.profile.eds}) has not",
                           "use the drive's EDS, or map objects it has")
            if var is None:
                report.add(name, False, missing[0], missing[1])
                continue
            where = f"0x{var.index:04X}.{var.subindex} {var.name!r}"
            problems, fixes = [], []
            if not var.pdo_mappable:
                problems.append("not PDO-mappable")
                fixes.append("map an object the EDS marks PDOMapping=1")
            bits = _BITS.get(var.data_type)
            if bits != spec.bits:
                problems.append(f"{bits} bits, the DBC signal {spec.bits}")
                fixes.append("make the DBC signal's size the object's")
            access = (var.access_type or "").lower()
            if not pdo.tx and access not in _WRITABLE:
                problems.append(f"access {access!r}: the gateway writes it (RPDO)")
                fixes.append("map a writable object in the RPDO")
            if pdo.tx and access not in _READABLE:
                problems.append(f"access {access!r}: the drive sends it (TPDO)")
                fixes.append("map a readable object in the TPDO")
            report.add(name, not problems, where + ("" if not problems else ": "
                                                   + "; ".join(problems)), "; ".join(fixes))


def _mappings(report: CheckReport, master: DriveMaster, pd: ProcessData, when: str) -> bool:
    ok = True
    for pdo in pd.pdos:
        try:
            problems = master.mapping_problems(pdo)
        except UserError as exc:
            problems = [str(exc)]
        ok &= report.add(f"mapping of {pdo.name} ({when})", not problems,
                         "; ".join(problems) or f"COB-ID 0x{pdo.cob_id:03X}, sizes "
                         f"{[s.bits for s in pdo.codec.signals]}",
                         "map the PDO on the drive as the profile's DBC says (COB-ID, objects "
                         "and sizes in order, enabled), or correct the DBC, or set remap = "
                         f"true in {master.profile.source}")
    return ok


def _roles(report: CheckReport, master: DriveMaster, pd: ProcessData) -> bool:
    from gateway.profilecheck import roles_needed

    mode = master.profile.check_mode
    roles = roles_needed(mode, pd)
    who = (f"a {mode} run" if mode.standard
           else f"the current-fed law with a {mode} drive")
    try:
        pd.require(roles, who, master.node.object_dictionary.indices)
    except UserError as exc:
        return report.add(f"roles of {who}", False, str(exc),
                          "map the missing roles in the profile's [signals]")
    return report.add(f"roles of {who}", True, ", ".join(roles))


class _Arrivals(can.Listener):
    """Arrival times (monotonic) of the TPDOs in the current cycle."""

    def __init__(self, cob_ids: set[int]) -> None:
        self.cob_ids = cob_ids
        self.lock = threading.Lock()
        self.seen: dict[int, float] = {}
        self.all = threading.Event()

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_extended_id or msg.arbitration_id not in self.cob_ids:
            return
        t = time.monotonic()
        with self.lock:
            self.seen.setdefault(msg.arbitration_id, t)
            if len(self.seen) == len(self.cob_ids):
                self.all.set()

    def reset(self) -> None:
        with self.lock:
            self.seen = {}
            self.all.clear()


def _pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, round(q * (len(s) - 1)))]


@dataclass
class _CycleTally:
    """What the SYNC cycles saw: ``n`` cycles sent, ``complete`` with every TPDO,
    ``in_period`` with every TPDO within the period, the current and the longest run of
    incomplete cycles, and each TPDO's arrival latencies after SYNC in s (``lat``, by
    COB-ID)."""

    lat: dict[int, list[float]]
    n: int = 0
    complete: int = 0
    in_period: int = 0
    run_missed: int = 0
    worst_run: int = 0

    def record(self, seen: dict[int, float], t0: float, period: float) -> None:
        """One cycle's arrivals (monotonic s, by COB-ID) after the SYNC sent at ``t0``."""
        for c, t in seen.items():
            self.lat[c].append(t - t0)
        if len(seen) == len(self.lat):
            self.complete += 1
            self.in_period += max(seen.values()) - t0 <= period
            self.run_missed = 0
        else:
            self.run_missed += 1
            self.worst_run = max(self.worst_run, self.run_missed)


def _zero_rpdos(pd: ProcessData) -> list[can.Message]:
    """The RPDOs the SYNC cycles send: zero setpoints, controlword 0 (disable voltage)."""
    values: dict[str, float] = {r: 0.0 for r in pd.roles}
    values["controlword"] = 0  # disable voltage: no power
    return [can.Message(arbitration_id=c, data=d, is_extended_id=False)
            for c, _, d in pd.encode(values)]


def _sync_and_wait(bus: can.BusABC, arrivals: _Arrivals, k: int, counter: bool,
                   timeout: float) -> tuple[float, dict[int, float]]:
    """Send SYNC ``k`` (with the counter byte if ``counter``) and wait for every TPDO, at
    most ``timeout`` s: the send time and the arrivals (monotonic s, by COB-ID)."""
    arrivals.reset()
    data = bytes([k % SYNC_OVERFLOW + 1]) if counter else b""
    t0 = time.monotonic()
    bus.send(can.Message(arbitration_id=SYNC_ID, data=data, is_extended_id=False))
    arrivals.all.wait(timeout)
    with arrivals.lock:
        seen = dict(arrivals.seen)
    return t0, seen


def _sync_cycles(report: CheckReport, master: DriveMaster, pd: ProcessData, bus: can.BusABC,
                 period: float, cycles: int, counter: bool) -> None:
    """SYNC in lockstep as a run does it (:class:`gateway.loop.CycleLoop`): SYNC, wait for
    every TPDO (at most the loop's ``tpdo_timeout``), the RPDOs, the next SYNC one period
    after the last; stops like a run after ``max_missed`` incomplete cycles in a row."""
    from gateway.loop import LoopConfig
    from gateway.spec import RunSpec

    tolerated = RunSpec()  # what a run tolerates before it stops
    timeout = LoopConfig(n_cycles=1).tpdo_timeout
    cob_ids = {p.cob_id: p.name for p in pd.tpdos}
    arrivals = _Arrivals(set(cob_ids))
    assert master.network.notifier is not None
    master.network.notifier.add_listener(arrivals)
    rpdos = _zero_rpdos(pd)
    tally = _CycleTally(lat={c: [] for c in cob_ids})
    try:
        t_next = time.monotonic()
        for k in range(cycles):
            if master.fault.is_set() or tally.run_missed > tolerated.max_missed:
                break
            t0, seen = _sync_and_wait(bus, arrivals, k, counter, timeout)
            tally.record(seen, t0, period)
            for m in rpdos:
                bus.send(m)
            tally.n += 1
            t_next = max(t_next + period, time.monotonic())
            time.sleep(max(0.0, t_next - time.monotonic()))
    finally:
        master.network.notifier.remove_listener(arrivals)
    report.cycles, report.complete_cycles = tally.n, tally.complete
    _report_latency(report, tally, cob_ids)
    report.notes.append(f"{tally.in_period} of {tally.n} cycles had every TPDO within the "
                        f"period ({period * 1e3:g} ms): what --timing realtime would see")
    faults = [f.describe() for f in master.state.faults]
    report.add("no drive fault during the SYNC cycles", not faults,
               "; ".join(faults) or "no EMCY, NMT change or lost heartbeat",
               "see the drive's EMCY / error history (0x1003) and its manual")
    _report_arrivals(report, tally, cob_ids, cycles, timeout, tolerated.max_missed,
                     tolerated.max_miss_rate)


def _report_latency(report: CheckReport, tally: _CycleTally, cob_ids: dict[int, str]) -> None:
    """Per TPDO (by name): COB-ID, how many arrived, median and p99 latency in µs."""
    for c, name in cob_ids.items():
        xs = tally.lat[c]
        report.latency[name] = {
            "cob_id": c, "received": len(xs),
            "median_us": statistics.median(xs) * 1e6 if xs else None,
            "p99_us": _pct(xs, 0.99) * 1e6 if xs else None}


def _report_arrivals(report: CheckReport, tally: _CycleTally, cob_ids: dict[int, str],
                     cycles: int, timeout: float, max_missed: int, max_miss_rate: float
                     ) -> None:
    """The check that every TPDO arrived (within ``timeout`` s) in all ``cycles`` SYNC
    cycles, passing within a run's tolerance (RunSpec ``max_missed`` incomplete cycles in
    a row, ``max_miss_rate``, a fraction)."""
    n, complete, worst_run = tally.n, tally.complete, tally.worst_run
    rate = (n - complete) / n if n else 1.0
    report.add(f"every TPDO in the {cycles} SYNC cycles",
               n == cycles and rate <= max_miss_rate and worst_run <= max_missed,
               f"{complete} of {n} cycles had {', '.join(cob_ids.values())} within "
               f"{timeout:g} s; at most {worst_run} incomplete in a row (a run stops beyond "
               f"{max_missed} in a row or a {max_miss_rate:.0%} rate)",
               "set the TPDOs' transmission type to 1 (every SYNC) and their COB-IDs as "
               "the DBC says, check the bus load and the period (--period) against the "
               "drive's cycle time")


def _statusword_power_off(report: CheckReport, master: DriveMaster, when: str) -> None:
    sw = master.statusword()
    state = State.from_statusword(sw)
    on = state is State.OPERATION_ENABLED
    report.power_stage_enabled |= on
    report.add(f"power stage off ({when})", not on,
               f"statusword 0x{sw:04X} ({state.name if state else 'unknown'})",
               "the drive is enabled by someone else: disable it before commissioning")


def check_drive(bus: can.BusABC, profile: DriveProfile, node: int | None = None,
                period: float = 0.001, cycles: int = 300,
                gateway_node: int | None = None) -> CheckReport:
    """Run the checks (module docstring) against the drive on ``bus``; the caller owns it."""
    pd = process_data(profile, node)
    master = DriveMaster(bus, profile, node, gateway_node)
    report = CheckReport(profile.source, master.node_id)
    try:
        try:
            master.connect()
            report.add("boot-up after NMT reset communication", True,
                       f"node {master.node_id} answered")
        except UserError as exc:
            if master.identity is None:  # refused before any NMT or write
                fix = (exc.fix if isinstance(exc, DeviceRefusedError) else
                       "check --node, power, wiring, bitrate (`hil-gateway scan`)")
                report.add("the device at the node is the profile's (0x1000, 0x1018)", False,
                           str(exc), fix)
                return report
            if not master._booted.is_set():
                report.add("boot-up after NMT reset communication", False, str(exc),
                           "check --node, power, wiring, bitrate (`hil-gateway scan`)")
                return report
            report.add("boot-up after NMT reset communication", True,
                       f"node {master.node_id} answered")
        _identity(report, master)
        _statusword_power_off(report, master, "before")
        _objects(report, master, pd)
        roles_ok = _roles(report, master, pd)
        mapped = True
        if not profile.remap:
            mapped = _mappings(report, master, pd, "read back")
        if not (mapped and roles_ok and report.ok):
            report.notes.append("not configured and no SYNC cycles: a check above failed")
            return report
        emulator: dict[str, int | float] = {}
        if profile.emulator:
            from gateway.runner import _eds_default

            emulator = {"Emulator model": DriveMode.CURRENT_LOOP.emulator_model,
                        "RPDO apply": int(Sampling(period).apply),
                        "f_pwm": round(internal_rate(_eds_default(master, "f_pwm"), period))}
        try:
            counter = master.configure(period, pd, profile.remap,
                                       profile.mode_of(profile.check_mode),
                                       emulator, sync_overflow=SYNC_OVERFLOW)
        except UserError as exc:
            report.add("configuration by SDO", False, str(exc),
                       "correct the profile against the drive's EDS")
            return report
        report.add("configuration by SDO", True, "PRE-OPERATIONAL configuration accepted")
        report.notes.extend(master.notes)
        if profile.remap:
            _mappings(report, master, pd, "written and read back")
        master.start()
        _sync_cycles(report, master, pd, bus, period, cycles, counter)
        _statusword_power_off(report, master, "after the SYNC cycles")
        return report
    finally:
        shut = master.shutdown()
        if shut is not None:
            report.add("shutdown confirms the power stage off", shut.safe,
                       "; ".join(shut.steps), "see the drive: it did not confirm power off")


# ------------------------------------------------------------------------------- CLI


def cmd_check(args: argparse.Namespace) -> int:
    from gateway.units import parse_duration

    period = parse_duration(args.period, "--period")
    if args.cycles < 1:
        raise UserError(f"--cycles {args.cycles}: give at least 1 SYNC cycle")
    profile = load_drive_profile(args.drive)
    process_data(profile, args.node)  # bad profile → exit 2 before the bus is opened
    if args.json:
        check_writable(Path(args.json), "--json")
    cfg = bus_config(args)
    try:
        bus = open_bus(cfg, receive_own_messages=False)
    except (can.CanError, OSError, ValueError) as exc:
        raise UserError(f"cannot open the bus {cfg.label()}: {exc}") from None
    try:
        report = check_drive(bus, profile, args.node, period, args.cycles, args.gateway_node)
    finally:
        bus.shutdown()
    print(report.text())
    if args.json:
        try:
            write_text_atomic(Path(args.json), json.dumps(report.to_json(), indent=2) + "\n")
        except OSError as exc:
            raise UserError(f"--json {args.json!r}: the report above could not be written "
                            f"({exc.strerror or exc}); choose another place") from None
    return 0 if report.ok else 1


def add_parser(sub: Any) -> None:
    """Register `check` on the subcommand parsers of `hil-gateway`."""
    p = sub.add_parser(
        "check", help="commission a drive without power: identity, objects, mappings, "
                      "roles, SYNC latency",
        description="Check a drive against its profile with the power stage off: boot-up, "
                    "device type and identity, the mapped objects in the EDS, the PDO "
                    "mappings read back over SDO, the roles of the current-fed law, then a "
                    "run's configuration and SYNC cycles with per-TPDO latency. Never "
                    "enables the drive. Exit status 0 if all pass, 1 if a check fails "
                    "(also: no drive at the node), 2 for bad input.")
    p.add_argument("--drive", metavar="PROFILE",
                   help="drive profile (TOML); default: the built-in emulator")
    p.add_argument("--node", type=int, help="node id (default: the profile's)")
    p.add_argument("--gateway-node", type=int, help="the gateway's node id (heartbeat)")
    p.add_argument("--cycles", type=int, default=300, help="SYNC cycles (default 300)")
    p.add_argument("--period", default="1ms", help="SYNC period (default 1ms)")
    p.add_argument("--json", metavar="FILE", help="write the report as JSON")
    add_bus_options(p)
    p.set_defaults(func=cmd_check)

