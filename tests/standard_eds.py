"""A CiA 402 drive's EDS (or DCF), written here from CiA 301/306/402 alone, for the twin tests
(tests/test_twin.py, tests/test_twin_two_process.py): a servo of another vendor, with
node-relative COB-IDs, default PDO mappings (RPDO1 controlword + target velocity, RPDO2
target torque (not valid), TPDO1 statusword + velocity actual value, TPDO2 torque actual
value + position actual value), the factor group (4096 increments per revolution), rated
torque and current, and a few objects no motor model backs.
"""

from __future__ import annotations

from pathlib import Path

BOOL, I8, I16, I32, U8, U16, U32, REAL32, VSTRING = 0x1, 0x2, 0x3, 0x4, 0x5, 0x6, 0x7, 0x8, 0x9
VENDOR, PRODUCT, REVISION, SERIAL = 0x00ABCDEF, 0x0000D402, 0x00020003, 0x12345678
DEVICE_TYPE = 0x00020192  #: CiA 402, servo drive
SUPPORTED = 0x000003A5  #: pp, pv, hm, csp, csv, cst
INCREMENTS = 4096  #: 0x608F, and 0x6092's feed per revolution: 1 unit = 1 increment
RATED_TORQUE_MNM, RATED_CURRENT_MA = 5000, 8000
#: The objects no model backs (index: name) and the values the file gives them.
STORAGE = {0x2000: ("Fan control", 3), 0x2300: ("Vendor counter", 7),
           0x605A: ("Quick stop option code", 2), 0x6073: ("Max current", 2000)}


def _var(name: str, dtype: int, access: str, default: str | None, pdo: bool = False,
         **extra: str) -> dict[str, str]:
    keys = {"ParameterName": name, "ObjectType": "0x7", "DataType": f"0x{dtype:04X}",
            "AccessType": access}
    if default is not None:
        keys["DefaultValue"] = default
    keys["PDOMapping"] = str(int(pdo))
    keys.update(extra)
    return keys


def _record(sections: dict, index: int, name: str, subs: list[dict[str, str]],
            otype: str = "0x9") -> None:
    sections[f"{index:04X}"] = {"ParameterName": name, "ObjectType": otype,
                                "SubNumber": str(len(subs))}
    for k, keys in enumerate(subs):
        sections[f"{index:04X}sub{k}"] = keys


def _pdo(sections: dict, comm: int, name: str, cob: str, entries: list[int]) -> None:
    _record(sections, comm, f"{name} communication parameter", [
        _var("Highest sub-index supported", U8, "const", "2"),
        _var("COB-ID", U32, "rw", cob),
        _var("Transmission type", U8, "rw", "1")])
    _record(sections, comm + 0x200, f"{name} mapping parameter", [
        _var("Number of mapped objects", U8, "rw", str(len(entries))),
        *(_var(f"Mapped object {k}", U32, "rw", f"0x{e:08X}")
          for k, e in enumerate([*entries, 0, 0][:max(2, len(entries))], 1))])


def sections() -> dict[str, dict[str, str]]:
    """The object sections of the drive's EDS, by section name."""
    s: dict[str, dict[str, str]] = {}
    s["1000"] = _var("Device type", U32, "ro", f"0x{DEVICE_TYPE:08X}")
    s["1001"] = _var("Error register", U8, "ro", "0")
    _record(s, 0x1003, "Pre-defined error field", [
        _var("Number of errors", U8, "rw", "0"),
        *(_var(f"Standard error field {k}", U32, "ro", "0") for k in range(1, 5))], "0x8")
    s["1005"] = _var("COB-ID SYNC", U32, "rw", "0x00000080")
    s["1006"] = _var("Communication cycle period", U32, "rw", "1000")
    s["1008"] = _var("Manufacturer device name", VSTRING, "const", "Std servo 402")
    s["100A"] = _var("Manufacturer software version", VSTRING, "const", "FW 3.4.5")
    s["1014"] = _var("COB-ID EMCY", U32, "rw", "$NODEID+0x80")
    s["1017"] = _var("Producer heartbeat time", U16, "rw", "100")
    _record(s, 0x1018, "Identity object", [
        _var("Highest sub-index supported", U8, "const", "4"),
        _var("Vendor-ID", U32, "ro", f"0x{VENDOR:08X}"),
        _var("Product code", U32, "ro", f"0x{PRODUCT:08X}"),
        _var("Revision number", U32, "ro", f"0x{REVISION:08X}"),
        _var("Serial number", U32, "ro", f"0x{SERIAL:08X}")])
    _pdo(s, 0x1400, "RPDO1", "$NODEID+0x200", [0x60400010, 0x60FF0020])
    _pdo(s, 0x1401, "RPDO2", "$NODEID+0x80000300", [0x60710010])
    _pdo(s, 0x1800, "TPDO1", "$NODEID+0x180", [0x60410010, 0x606C0020])
    _pdo(s, 0x1801, "TPDO2", "$NODEID+0x280", [0x60770010, 0x60640020])
    s["2000"] = _var(STORAGE[0x2000][0], U8, "rw", str(STORAGE[0x2000][1]))
    _record(s, 0x2001, "Vendor tuning", [
        _var("Highest sub-index supported", U8, "const", "2"),
        _var("Gain", I16, "rw", "-12", LowLimit="-100", HighLimit="100"),
        _var("Filter", REAL32, "rw", "1.5")])
    s["2300"] = _var(STORAGE[0x2300][0], U32, "ro", str(STORAGE[0x2300][1]))
    s["603F"] = _var("Error code", U16, "ro", "0", pdo=True)
    s["6040"] = _var("Controlword", U16, "rww", "0", pdo=True)
    s["6041"] = _var("Statusword", U16, "ro", "0", pdo=True)
    s["605A"] = _var(STORAGE[0x605A][0], I16, "rw", str(STORAGE[0x605A][1]))
    s["6060"] = _var("Modes of operation", I8, "rw", "0")
    s["6061"] = _var("Modes of operation display", I8, "ro", "0", pdo=True)
    s["6064"] = _var("Position actual value", I32, "ro", "0", pdo=True)
    s["606C"] = _var("Velocity actual value", I32, "ro", "0", pdo=True)
    s["6071"] = _var("Target torque", I16, "rww", "0", pdo=True)
    s["6072"] = _var("Max torque", U16, "rw", "3000")
    s["6073"] = _var(STORAGE[0x6073][0], U16, "rw", str(STORAGE[0x6073][1]))
    s["6075"] = _var("Motor rated current", U32, "rw", str(RATED_CURRENT_MA))
    s["6076"] = _var("Motor rated torque", U32, "rw", str(RATED_TORQUE_MNM))
    s["6077"] = _var("Torque actual value", I16, "ro", "0", pdo=True)
    s["6078"] = _var("Current actual value", I16, "ro", "0", pdo=True)
    s["6079"] = _var("DC link circuit voltage", U32, "ro", "0", pdo=True)
    s["607A"] = _var("Target position", I32, "rww", "0", pdo=True)
    _record(s, 0x608F, "Position encoder resolution", [
        _var("Highest sub-index supported", U8, "const", "2"),
        _var("Encoder increments", U32, "rw", str(INCREMENTS)),
        _var("Motor revolutions", U32, "rw", "1")])
    _record(s, 0x6091, "Gear ratio", [
        _var("Highest sub-index supported", U8, "const", "2"),
        _var("Motor revolutions", U32, "rw", "1"),
        _var("Shaft revolutions", U32, "rw", "1")])
    _record(s, 0x6092, "Feed constant", [
        _var("Highest sub-index supported", U8, "const", "2"),
        _var("Feed", U32, "rw", str(INCREMENTS)),
        _var("Shaft revolutions", U32, "rw", "1")])
    s["60FF"] = _var("Target velocity", I32, "rww", "0", pdo=True)
    s["6502"] = _var("Supported drive modes", U32, "ro", f"0x{SUPPORTED:08X}")
    return s


def write_drive_file(path: Path, objects: dict[str, dict[str, str]] | None = None,
                     node_id: int | None = None, device_info: dict[str, str] | None = None
                     ) -> Path:
    """Write the EDS (a DCF when ``path`` ends in .dcf: ``node_id`` goes to its
    [DeviceComissioning]); ``objects``: the sections (default :func:`sections`);
    ``device_info``: keys that replace [DeviceInfo]'s."""
    objs = sections() if objects is None else objects
    info = {"VendorName": "Test Drives", "VendorNumber": f"0x{VENDOR:08X}",
            "ProductName": "Std servo 402", "ProductNumber": f"0x{PRODUCT:08X}",
            "RevisionNumber": f"0x{REVISION:08X}", "OrderCode": "SS-402",
            **{f"BaudRate_{k}": "1" for k in (125, 250, 500, 1000)},
            "SimpleBootUpSlave": "1", "Granularity": "8", "NrOfRXPDO": "2", "NrOfTXPDO": "2",
            "LSS_Supported": "0", **(device_info or {})}
    lines = ["[FileInfo]", f"FileName={path.name}", "FileVersion=1", "FileRevision=0",
             "EDSVersion=4.0", "Description=CiA 402 servo written from the standard", "",
             "[DeviceInfo]", *(f"{k}={v}" for k, v in info.items()), ""]
    if node_id is not None:
        lines += ["[DeviceComissioning]", f"NodeID={node_id}", "NodeName=axis", "Baudrate=500",
                  ""]
    mandatory = [s for s in objs if s in ("1000", "1001", "1018")]
    optional = [s for s in objs if len(s) == 4 and s not in mandatory
                and not 0x2000 <= int(s, 16) < 0x6000]
    manufacturer = [s for s in objs if len(s) == 4 and 0x2000 <= int(s, 16) < 0x6000]
    for group, members in (("MandatoryObjects", mandatory), ("OptionalObjects", optional),
                           ("ManufacturerObjects", manufacturer)):
        lines += [f"[{group}]", f"SupportedObjects={len(members)}",
                  *(f"{k}=0x{m}" for k, m in enumerate(members, 1)), ""]
    for name, keys in objs.items():
        lines += [f"[{name}]", *(f"{k}={v}" for k, v in keys.items()), ""]
    path.write_text("\n".join(lines), encoding="ascii")
    return path
