"""dbc/drive.eds as CiA 306 and as third-party readers see it.

Three readers load it: python-canopen (what the gateway and the emulator use), objdictgen
(CanFestival's dictionary tool) and eds-utils (the CANopenNode-style EDS tool set); their
object lists, types and defaults agree. A lint of our own checks the CiA 306 layout: nothing
before the first section, only CiA 306 keys per section, [FileInfo]/[DeviceInfo] complete,
the object lists consistent, limits integers of the declared type.
"""

from __future__ import annotations

import re
import struct
from datetime import datetime

import canopen
import pytest
from canopen.objectdictionary import ODVariable, datatypes

import dbc

# ---- the lint ----------------------------------------------------------------------------------

FILE_INFO_KEYS = ("FileName", "FileVersion", "FileRevision", "EDSVersion", "Description",
                  "CreationTime", "CreationDate", "CreatedBy", "ModificationTime",
                  "ModificationDate", "ModifiedBy")
DEVICE_INFO_KEYS = ("VendorName", "VendorNumber", "ProductName", "ProductNumber",
                    "RevisionNumber", "OrderCode",
                    *(f"BaudRate_{k}" for k in (10, 20, 50, 125, 250, 500, 800, 1000)),
                    "SimpleBootUpMaster", "SimpleBootUpSlave", "Granularity",
                    "DynamicChannelsSupported", "GroupMessaging", "NrOfRXPDO", "NrOfTXPDO",
                    "LSS_Supported")
#: Keys CiA 306 defines per kind of section (DCF-only keys included where harmless).
ALLOWED: dict[str, set[str] | re.Pattern[str]] = {
    "FileInfo": {*FILE_INFO_KEYS, "LastEDS"},
    "DeviceInfo": {*DEVICE_INFO_KEYS, "CompactPDO", "CANopenSafetySupported"},
    "DummyUsage": re.compile(r"Dummy000[1-7]"),
    "Comments": re.compile(r"Lines|Line[1-9][0-9]*"),
    "MandatoryObjects": re.compile(r"SupportedObjects|[1-9][0-9]*"),
    "OptionalObjects": re.compile(r"SupportedObjects|[1-9][0-9]*"),
    "ManufacturerObjects": re.compile(r"SupportedObjects|[1-9][0-9]*"),
}
OBJECT_KEYS = {"ParameterName", "ObjectType", "DataType", "AccessType", "DefaultValue",
               "LowLimit", "HighLimit", "PDOMapping", "SubNumber", "ObjFlags", "CompactSubObj"}
INT_RANGES = {0x1: (0, 1), 0x2: (-2**7, 2**7 - 1), 0x3: (-2**15, 2**15 - 1),
              0x4: (-2**31, 2**31 - 1), 0x5: (0, 2**8 - 1), 0x6: (0, 2**16 - 1),
              0x7: (0, 2**32 - 1)}
REAL32 = 0x8
RE_OBJECT = re.compile(r"([0-9A-F]{4})(?:sub([0-9A-F]{1,2}))?")
RE_INT = re.compile(r"-?(0x[0-9A-Fa-f]+|[1-9][0-9]*|0)")


def parse_sections(text: str) -> list[tuple[str, list[tuple[str, str]]]]:
    """The sections in order as (name, [(key, value)]); raises on text before the first."""
    sections: list[tuple[str, list[tuple[str, str]]]] = []
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.startswith(";"):
            assert sections, f"line {n}: a comment before the first section"
            continue
        if line.startswith("["):
            assert line.endswith("]"), f"line {n}: {line!r}"
            sections.append((line[1:-1], []))
            continue
        assert sections, f"line {n}: {line!r} before the first section"
        key, sep, value = line.partition("=")
        assert sep and "=" not in value, f"line {n}: {line!r} needs exactly one '='"
        sections[-1][1].append((key, value))
    return sections


def int_value(value: str) -> int:
    assert RE_INT.fullmatch(value), f"{value!r} is not a decimal or 0x integer"
    return int(value, 0)


def lint(text: str) -> list[str]:
    """CiA 306 problems of an EDS text (empty when none)."""
    problems: list[str] = []
    sections = parse_sections(text)
    names = [s for s, _ in sections]
    if names[:1] != ["FileInfo"]:
        problems.append(f"the first section is [{names[0]}], not [FileInfo]")
    dupes = {s for s in names if names.count(s) > 1}
    if dupes:
        problems.append(f"sections twice: {sorted(dupes)}")
    by_name = {s: dict(kv) for s, kv in sections}
    objects: dict[int, dict[str, str]] = {}
    subs: dict[int, dict[int, dict[str, str]]] = {}
    for name, kv in sections:
        keys = [k for k, _ in kv]
        if len(set(keys)) != len(keys):
            problems.append(f"[{name}]: a key twice")
        m = RE_OBJECT.fullmatch(name)
        if m:
            unknown = set(keys) - OBJECT_KEYS
            if m.group(2) is None:
                objects[int(m.group(1), 16)] = dict(kv)
            else:
                subs.setdefault(int(m.group(1), 16), {})[int(m.group(2), 16)] = dict(kv)
        elif name in ALLOWED:
            allowed = ALLOWED[name]
            unknown = {k for k in keys if (k not in allowed if isinstance(allowed, set)
                                           else not allowed.fullmatch(k))}
        else:
            problems.append(f"[{name}] is not a CiA 306 section")
            continue
        if unknown:
            problems.append(f"[{name}]: keys outside CiA 306: {sorted(unknown)}")
    for section, required in (("FileInfo", FILE_INFO_KEYS), ("DeviceInfo", DEVICE_INFO_KEYS)):
        missing = [k for k in required if k not in by_name.get(section, {})]
        if missing:
            problems.append(f"[{section}] lacks {missing}")
    fi = by_name.get("FileInfo", {})
    for t, d in (("CreationTime", "CreationDate"), ("ModificationTime", "ModificationDate")):
        try:
            datetime.strptime(f"{fi.get(d)} {fi.get(t)}", "%m-%d-%Y %I:%M%p")
        except ValueError:
            problems.append(f"[FileInfo] {t}/{d} are not hh:mm(AM|PM) / mm-dd-yyyy")
    if fi.get("EDSVersion") != "4.0":
        problems.append("[FileInfo] EDSVersion is not 4.0")
    comments = by_name.get("Comments")
    if comments is not None and int(comments.get("Lines", "0"), 0) != len(comments) - 1:
        problems.append("[Comments] Lines does not count the lines")
    # object lists: each object once, in the list of its range, counts right
    listed: dict[str, list[int]] = {}
    for group in ("MandatoryObjects", "OptionalObjects", "ManufacturerObjects"):
        kv = by_name.get(group, {})
        entries = [int(kv[str(k)], 0) for k in range(1, int(kv.get("SupportedObjects", "0"), 0)
                                                    + 1) if str(k) in kv]
        if len(entries) != len(kv) - 1:
            problems.append(f"[{group}] SupportedObjects does not count 1..N")
        listed[group] = entries
    want = {
        "MandatoryObjects": {i for i in objects if i in (0x1000, 0x1001, 0x1018)},
        "OptionalObjects": {i for i in objects if (0x1000 <= i < 0x2000 or i >= 0x6000)
                            and i not in (0x1000, 0x1001, 0x1018)},
        "ManufacturerObjects": {i for i in objects if 0x2000 <= i < 0x6000},
    }
    for group, entries in listed.items():
        if sorted(entries) != sorted(want[group]):
            problems.append(f"[{group}] lists {sorted(map(hex, entries))}, the objects are "
                            f"{sorted(map(hex, want[group]))}")
    if not {0x1000, 0x1001, 0x1018} <= set(objects):
        problems.append("0x1000, 0x1001 and 0x1018 are mandatory")
    # objects: SubNumber, types, limits
    for index, obj in objects.items():
        otype = int(obj.get("ObjectType", "0x7"), 0)
        variables = [(f"{index:04X}", obj)] if otype == 0x7 else [
            (f"{index:04X}sub{s:X}", v) for s, v in sorted(subs.get(index, {}).items())]
        if otype in (0x8, 0x9) and int(obj.get("SubNumber", "-1"), 0) != len(variables):
            problems.append(f"[{index:04X}] SubNumber is not the number of sub-indices")
        for section, v in variables:
            dtype = int(v.get("DataType", "0"), 0)
            if v.get("AccessType", "").lower() not in ("ro", "wo", "rw", "rwr", "rww", "const"):
                problems.append(f"[{section}] AccessType {v.get('AccessType')!r}")
            limits = {}
            for key in ("LowLimit", "HighLimit"):
                if key not in v:
                    continue
                try:
                    limits[key] = int_value(v[key])
                except AssertionError as exc:  # REAL32 too: objdictgen takes integers only
                    problems.append(f"[{section}] {key}: {exc}")
                    continue
                if dtype in INT_RANGES:
                    lo, hi = INT_RANGES[dtype]
                    value = limits[key]
                    bits = {0x2: 8, 0x3: 16, 0x4: 32}.get(dtype)
                    if bits and v[key].startswith("0x") and value > hi:  # two's complement
                        value -= 1 << bits
                    if not lo <= value <= hi:
                        problems.append(f"[{section}] {key}={v[key]} is outside the type")
                elif dtype != REAL32:
                    problems.append(f"[{section}] {key} on a non-numeric type")
            if len(limits) == 2 and limits["LowLimit"] > limits["HighLimit"]:
                problems.append(f"[{section}] LowLimit > HighLimit")
    return problems


def test_lint_passes():
    assert lint(dbc.EDS_PATH.read_text(encoding="ascii")) == []


@pytest.mark.parametrize("edit, problem", [
    (lambda t: "; generated\n" + t, "before the first section"),
    (lambda t: t.replace("ParameterName=J\n", "ParameterName=J\nDescription=kg.m^2\n"),
     "keys outside CiA 306: ['Description']"),
    (lambda t: t.replace("ModifiedBy=", "X=").replace("X=can-drive-hil tools/gen_eds.py\n", ""),
     "[FileInfo] lacks ['ModifiedBy']"),
    (lambda t: t.replace("ParameterName=J\n", "ParameterName=J\nLowLimit=1e-05\n"),
     "is not a decimal or 0x integer"),
    (lambda t: t.replace("HighLimit=240", "HighLimit=256"), "outside the type"),
    (lambda t: t.replace("3=0x1018\n", ""), "[MandatoryObjects]"),
])
def test_lint_finds(edit, problem):
    text = dbc.EDS_PATH.read_text(encoding="ascii")
    try:
        found = lint(edit(text))
    except AssertionError as exc:
        found = [str(exc)]
    assert any(problem in p for p in found), found


# ---- the readers -------------------------------------------------------------------------------


def _canopen_vars() -> dict[tuple[int, int], ODVariable]:
    od = canopen.import_od(str(dbc.EDS_PATH), 1)
    out = {}
    for obj in od.values():
        for v in [obj] if isinstance(obj, ODVariable) else obj.values():
            out[(v.index, v.subindex)] = v
    return out


def _same(a, b, dtype: int) -> bool:
    if dtype == datatypes.REAL32:
        return struct.pack("<f", float(a)) == struct.pack("<f", float(b))
    return a == b


def test_canopen_loads_every_object():
    vars_ = _canopen_vars()
    # 0x2201 has 9 subs (w_max); 0x2205 time base; 8 CSP/CSV/CST objects; 11 PV/PT objects
    assert len(vars_) == 182
    assert vars_[(0x2201, 1)].default == 560.0 and vars_[(0x6079, 0)].default == 560000
    assert vars_[(0x1014, 0)].default == 0x81  # $NODEID+0x80 for node 1
    assert (vars_[(0x6060, 0)].min, vars_[(0x6060, 0)].max) == (-2, 10)  # -2, -1, 9, 10
    # PV, PT, CSP, CSV, CST, both vector modes
    assert vars_[(0x6502, 0)].default == 0x0003038C
    assert (vars_[(0x2201, 1)].min, vars_[(0x2201, 1)].max) == (10, 1300)


def test_emulator_keeps_its_real32_ranges():
    from plant.od import REAL32_LIMITS, ObjectStore

    store = ObjectStore(1)
    for key, rng in REAL32_LIMITS.items():
        assert store.limits[key] == rng
    assert store.limits[(0x2201, 8)] == (1000.0, 100000.0)  # UNSIGNED32 from the EDS


def test_objdictgen_reads_the_same_objects():
    from objdictgen import eds_utils

    node = eds_utils.generate_node(str(dbc.EDS_PATH), 1)
    vars_ = _canopen_vars()
    assert set(node.GetIndexes()) == {i for i, _ in vars_}
    for (index, sub), v in vars_.items():
        info = node.GetSubentryInfos(index, sub)
        assert info["type"] == v.data_type, (hex(index), sub)
        if sub == 0 and not isinstance(v.parent, canopen.ObjectDictionary):
            # objdictgen makes sub-index 0 the number of entries it holds (8 for a PDO
            # mapping), not the EDS default (the number of mapped objects), and names it
            continue
        value = node.GetEntry(index, sub)
        assert _same(value, v.default, v.data_type), (hex(index), sub, value, v.default)
        # standard objects get objdictgen's own names ("Controlword" for 0x6040)
        assert info["name"].casefold() == v.name.casefold()


def test_eds_utils_reads_the_same_objects():
    from eds_utils.core.file_io.read_eds import read_eds

    eds, errors = read_eds(str(dbc.EDS_PATH))
    assert errors == []
    vars_ = _canopen_vars()
    assert set(eds.indexes) == {i for i, _ in vars_}
    for (index, sub), v in vars_.items():
        obj = eds[index]
        e = obj if isinstance(v.parent, canopen.ObjectDictionary) else obj[sub]
        assert e.parameter_name == v.name
        assert int(e.data_type) == v.data_type
        assert e.access_type.name.lower() == v.access_type
        assert e.pdo_mapping == v.pdo_mappable
        raw = e.default_value.replace("$NODEID+", "")
        value: object = raw
        if v.data_type == datatypes.REAL32:
            value = float(raw)
        elif v.data_type in INT_RANGES:
            value = int(raw, 0) + (1 if "$NODEID" in e.default_value else 0)
        if sub == 0 and not isinstance(v.parent, canopen.ObjectDictionary):
            continue  # eds-utils too makes sub-index 0 the highest sub-index it holds
        assert _same(value, v.default, v.data_type), (hex(index), sub, raw, v.default)
