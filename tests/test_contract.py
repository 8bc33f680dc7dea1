"""The PDO contract: dbc/drive.eds default mappings agree with dbc/drive.dbc, and the fast
codec agrees with cantools."""

from __future__ import annotations

import importlib.util
import math
import sys
import timeit
from pathlib import Path

import canopen
import pytest
from canopen.objectdictionary import datatypes
from hypothesis import given, settings
from hypothesis import strategies as st

import dbc
from dbc.cia301 import is_service


def _load_tool(name: str):
    """A development tool of tools/ (not an installed module)."""
    path = Path(__file__).resolve().parents[1] / "tools" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


gen_eds = _load_tool("gen_eds")

RPDO_DEFAULTS = {"RPDO1": 1, "RPDO2": 2, "RPDO3": 3}
TPDO_DEFAULTS = {"TPDO1": 1, "TPDO2": 2, "TPDO3": 3}
BITS = {datatypes.UNSIGNED8: (8, False), datatypes.UNSIGNED16: (16, False),
        datatypes.INTEGER16: (16, True), datatypes.INTEGER8: (8, True)}


@pytest.fixture(scope="module")
def db():
    """drive.dbc with the alternative mapping of its (a, b) companion drive_ab.dbc."""
    return dbc.load_database()


@pytest.fixture(scope="module")
def od():
    return canopen.import_od(str(dbc.EDS_PATH), 1)


def _mapping(od, index):
    rec = od[index]
    n = rec[0].default
    out = []
    for k in range(1, n + 1):
        e = rec[k].default
        out.append((e >> 16, (e >> 8) & 0xFF, e & 0xFF))
    return out


@pytest.mark.parametrize("name", [*RPDO_DEFAULTS, *TPDO_DEFAULTS])
def test_default_mappings_equal_dbc_messages(db, od, name):
    rx = name.startswith("R")
    n = (RPDO_DEFAULTS | TPDO_DEFAULTS)[name]
    comm = od[(0x1400 if rx else 0x1800) + n - 1]
    msg = db.get_message_by_name(name)
    assert comm[1].default & 0x7FF == msg.frame_id  # node 1
    assert comm[1].default & 0x80000000 == 0  # valid
    mapping = _mapping(od, (0x1600 if rx else 0x1A00) + n - 1)
    sigs = sorted(msg.signals, key=lambda s: s.start)
    assert len(mapping) == len(sigs)
    bit = 0
    for (index, sub, length), sig in zip(mapping, sigs, strict=True):
        obj = od[index] if sub == 0 else od[index][sub]
        assert obj.name == sig.name
        assert obj.pdo_mappable
        assert length == sig.length == BITS[obj.data_type][0]
        assert sig.is_signed == BITS[obj.data_type][1]
        assert sig.start == bit and sig.byte_order == "little_endian"
        bit += length
        assert obj.writable == rx  # RPDO objects writable, TPDO objects read-only
    assert bit == 8 * msg.length


def test_alternative_rpdo2_ab_objects_exist(db, od):
    msg = db.get_message_by_name("RPDO2_AB")
    assert msg.frame_id == db.get_message_by_name("RPDO2").frame_id
    for sig in msg.signals:
        obj = od[sig.name]
        assert obj.pdo_mappable and obj.writable
        assert BITS[obj.data_type] == (sig.length, sig.is_signed)


def test_every_signal_has_an_object_and_vice_versa(db, od):
    """Every signal of the DBC is an object of the emulator's own; the other mappable
    objects are CiA 402's standard ones, whose PDOs carry the raw values in the units of
    the EDS (the emulator packs them by data type)."""
    signals = {s.name for m in db.messages if not is_service(m.frame_id) for s in m.signals}
    mappable = {o.name for o in od.values()
                if isinstance(o, canopen.objectdictionary.ODVariable) and o.pdo_mappable}
    standard = {od[i].name for i in (0x6064, 0x606B, 0x606C, 0x6071, 0x6074, 0x6077, 0x607A,
                                      0x6083, 0x6084, 0x6087, 0x60FF)}
    assert signals == mappable - standard
    assert set(gen_eds.SIGNAL_INDEX) == signals


def test_committed_eds_is_generated():
    assert dbc.EDS_PATH.read_text(encoding="ascii") == gen_eds.render()


def test_required_objects(od):
    assert od[0x1000].default == 0x00010192
    assert od[0x1005].default == 0x80
    assert od[0x1006].default == 1000
    for index in (0x1001, 0x1003, 0x1007, 0x1014, 0x1016, 0x1017, 0x1018, 0x1019, 0x6040,
                  0x6041, 0x6060, 0x6061, 0x6079, 0x2200, 0x2201, 0x2202, 0x2203):
        assert index in od
    assert od[0x1014].default == 0x81
    for n in range(3):
        assert 5 in od[0x1400 + n]  # RPDO event timer = deadline monitoring
        assert od[0x1800 + n][2].default == 1  # every SYNC
    for name in ("J", "R_s", "R_r", "L_s", "L_r", "M"):
        assert od[0x2200][name].data_type == datatypes.REAL32


def test_codec_matches_cantools(db):
    codec = dbc.load_codec()
    for name in codec.names:
        msg = db.get_message_by_name(name)
        assert codec.frame_id(name) == msg.frame_id
        values = {s.name: (s.scale * 123 if s.name not in dbc.INT_SIGNALS else 7)
                  for s in msg.signals}
        data = codec.encode(name, values)
        assert len(data) == msg.length
        decoded = msg.decode(data, decode_choices=False)
        mine = codec.decode(name, data)
        assert set(decoded) == set(mine)
        for k, v in mine.items():
            assert decoded[k] == pytest.approx(v, rel=1e-12, abs=1e-12)


def test_node_id_offsets():
    c5 = dbc.load_codec(5)
    assert c5.frame_id("RPDO1") == 0x205 and c5.frame_id("TPDO3") == 0x385
    assert c5.by_frame_id[0x305] == "RPDO2"
    with pytest.raises(ValueError):
        dbc.load_codec(0)


def test_saturation_rounding_and_wrap():
    c = dbc.load_codec()
    q = c.quantize("RPDO2", {"i_sd_ref": 1e9, "i_sq_ref": -1e9, "u_sd_ref": 0.0101,
                             "u_sq_ref": math.inf})
    assert q["i_sd_ref"] == pytest.approx(32.767) and q["i_sq_ref"] == pytest.approx(-32.768)
    assert q["u_sd_ref"] == pytest.approx(0.02) and q["u_sq_ref"] == pytest.approx(655.34)
    f = 2 * math.pi / 65536
    e = c.quantize("RPDO1", {"controlword": 0x0F, "eps_0": -f, "w_0": 0.0})["eps_0"]
    assert e == pytest.approx(2 * math.pi - f)
    e = c.quantize("RPDO1", {"controlword": 0x0F, "eps_0": 4 * math.pi + 3 * f, "w_0": 0.0})
    assert e["eps_0"] == pytest.approx(3 * f)
    assert isinstance(e["controlword"], int)
    with pytest.raises(ValueError):
        c.encode("RPDO3", {"T_L": math.nan})
    with pytest.raises(KeyError):
        c.encode("RPDO3", {})


def test_scaling():
    assert dbc.scaling("i_sa") == (0.001, 16, True)
    assert dbc.scaling("u_dc") == (0.02, 16, False)
    assert dbc.scaling("eps_0") == (2 * math.pi / 65536, 16, False)
    with pytest.raises(KeyError, match="known"):
        dbc.scaling("nope")


@settings(max_examples=300, deadline=None)
@given(st.lists(st.integers(-(2**15), 2**15 - 1), min_size=4, max_size=4))
def test_decode_encode_is_identity_on_raw(raws):
    c = dbc.load_codec()
    data = c.messages["RPDO2"].pack(*raws)
    assert c.encode("RPDO2", c.decode("RPDO2", data)) == data


@settings(max_examples=300, deadline=None)
@given(st.floats(-100, 100), st.floats(-1000, 1000))
def test_quantize_is_nearest(i, u):
    c = dbc.load_codec()
    q = c.quantize("RPDO2_AB", {"i_sa_ref": i, "i_sb_ref": 0.0, "u_sa_ref": u, "u_sb_ref": 0.0})
    if abs(i) < 32.7:
        assert abs(q["i_sa_ref"] - i) <= 0.0005 + 1e-12
    if abs(u) < 655:
        assert abs(q["u_sa_ref"] - u) <= 0.01 + 1e-12


def test_codec_is_fast():
    c = dbc.load_codec()
    v = {"statusword": 0x237, "i_sa": 1.0, "i_sb": -2.0, "sync_counter": 3}
    data = c.encode("TPDO1", v)
    n = 20000
    t_enc = min(timeit.repeat(lambda: c.encode("TPDO1", v), number=n, repeat=3)) / n
    t_dec = min(timeit.repeat(lambda: c.decode("TPDO1", data), number=n, repeat=3)) / n
    assert t_enc < 10e-6 and t_dec < 10e-6  # target 3 us; generous for loaded CI machines
