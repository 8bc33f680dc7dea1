"""The bus time of a drive profile's cycle, and the refusal of a period it cannot fit.

One cycle of the gateway's process data is: the SYNC (with its counter byte), every TPDO
the drive sends on it (every ``transmission_type``-th SYNC) and every RPDO the gateway
answers with (every cycle). Their worst-case bits (:mod:`dbc.busload`) at the profile's
bit rate are the cycle's bus time; `sim` and `run` refuse a period in which that takes
more than :data:`dbc.busload.LOAD_LIMIT`, before the bus opens.
"""

from __future__ import annotations

from dbc.busload import LOAD_LIMIT, CycleFrame, CycleLoad, cycle_load
from gateway.drive_profile import DriveProfile
from gateway.errors import UserError
from gateway.process_data import ProcessData, process_data


def profile_load(drive: DriveProfile, pd: ProcessData | None = None,
                 sync_counter: bool = True) -> CycleLoad:
    """The frames of one cycle of ``drive``'s mapping: SYNC (1 byte with a counter, else
    0), its TPDOs, its RPDOs, at its [drive].bitrate."""
    pd = pd if pd is not None else process_data(drive)
    tt = drive.transmission_type
    frames = [CycleFrame("SYNC", 1 if sync_counter else 0)]
    frames += [CycleFrame(p.name, p.length, tt) for p in pd.tpdos]
    frames += [CycleFrame(p.name, p.length) for p in pd.rpdos]
    return cycle_load(frames, drive.bitrate)


def check_bus_time(drive: DriveProfile, period: float, pd: ProcessData | None = None,
                   lean: str = "--mapping lean") -> CycleLoad:
    """Refuse (:class:`UserError`) a period the drive's cycle does not fit: its bus time
    above :data:`LOAD_LIMIT` of the period; and TPDOs not sent every SYNC, which the loop
    cannot take. ``lean``: how to choose a leaner mapping, for the message."""
    load = profile_load(drive, pd)
    if drive.transmission_type != 1:
        raise UserError(f"{drive.source}: [pdo].transmission_type = "
                        f"{drive.transmission_type}: the loop takes a sample from the drive's "
                        "TPDOs on every SYNC; set it to 1")
    if not load.fits(period):
        us = period * 1e6
        raise UserError(
            f"the cycle's frames do not fit the period: {load.busiest_bits} bits = "
            f"{load.busiest_time * 1e6:.0f} us of bus time at "
            f"{load.bitrate / 1e6:g} Mbit/s (worst-case stuffing) in a {us:g} us period is a "
            f"bus load of {load.load(period):.0%}, above the {LOAD_LIMIT:.0%} limit "
            f"({drive.name}, {len(load.frames)} frames a cycle). Use a period of at least "
            f"{load.min_period() * 1e6:.0f} us, or a leaner mapping ({lean}); "
            "--allow-bus-overload runs it anyway (sim: its in-process bus has no bit rate)")
    return load
