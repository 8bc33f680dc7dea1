"""The codec takes every PDO form a DBC allows (dbc/codec.py, dbc/frame.py): Motorola byte
order, any start bit and length 1..64, 24-bit integers, REAL32/REAL64, offsets, gaps and
padding. Each form matches cantools' own encode/decode bit for bit, quantises by the fast
path's rule (round to nearest, saturate at the raw range, wrap for angles), and a drive
profile whose DBC uses them loads and runs its process data through the gateway's code.
What the codec cannot take is refused by name."""

from __future__ import annotations

import math
import random
import struct
from pathlib import Path

import can
import cantools
import pytest

from dbc import load_codec
from dbc.codec import MessageCodec, parse_dbc
from dbc.frame import SignalSpec
from gateway.buslog import decode_frames
from gateway.cli import main
from gateway.drive_profile import load_drive_profile
from gateway.errors import UserError
from gateway.process_data import process_data

HEADER = """VERSION ""


NS_ :
	CM_
	VAL_
	SIG_VALTYPE_

BS_:

BU_: GATEWAY DRIVE


"""

#: One message per form (ids of node 1).
FORMS = HEADER + """BO_ 385 BIG_ENDIAN: 8 DRIVE
 SG_ be_i16 : 7|16@0- (0.001,0) [-32.768|32.767] "A" GATEWAY
 SG_ be_u12 : 19|12@0+ (0.5,0) [0|2047.5] "V" GATEWAY
 SG_ be_i32 : 39|32@0- (0.0001,0) [0|0] "" GATEWAY

BO_ 641 BIT_PACKED: 8 DRIVE
 SG_ bp_u1 : 0|1@1+ (1,0) [0|1] "" GATEWAY
 SG_ bp_i3 : 1|3@1- (1,0) [-4|3] "" GATEWAY
 SG_ bp_i13 : 4|13@1- (0.01,0) [0|0] "" GATEWAY
 SG_ bp_u47 : 17|47@1+ (1e-06,0) [0|0] "" GATEWAY

BO_ 897 INT24: 6 DRIVE
 SG_ i24 : 0|24@1- (0.001,0) [0|0] "A" GATEWAY
 SG_ u24 : 24|24@1+ (0.01,0) [0|0] "V" GATEWAY

BO_ 1153 REAL32: 8 DRIVE
 SG_ r32 : 0|32@1- (1,0) [0|0] "rad/s" GATEWAY
 SG_ r32_scaled : 32|32@1- (0.5,10) [0|0] "N.m" GATEWAY

BO_ 513 REAL64: 8 GATEWAY
 SG_ r64 : 0|64@1- (1,0) [0|0] "rad" DRIVE

BO_ 769 OFFSET: 4 GATEWAY
 SG_ temp : 0|16@1+ (0.1,-40) [-40|6513.5] "degC" DRIVE
 SG_ off_i16 : 16|16@1- (0.02,100) [0|0] "V" DRIVE

BO_ 1025 PADDED: 8 GATEWAY
 SG_ pad_a : 8|16@1- (0.001,0) [0|0] "A" DRIVE
 SG_ pad_b : 40|8@1+ (1,0) [0|255] "" DRIVE

BO_ 1281 INT64: 8 GATEWAY
 SG_ i64 : 0|64@1- (1,0) [0|0] "" DRIVE

BO_ 1537 SDO_REQUEST: 8 GATEWAY
 SG_ sdo_command : 0|8@1+ (1,0) [0|255] "" DRIVE
 SG_ sdo_index : 8|16@1+ (1,0) [0|65535] "" DRIVE
 SG_ sdo_subindex : 24|8@1+ (1,0) [0|255] "" DRIVE
 SG_ sdo_data : 32|32@1+ (1,0) [0|4294967295] "" DRIVE


SIG_VALTYPE_ 1153 r32 : 1;
SIG_VALTYPE_ 1153 r32_scaled : 1;
SIG_VALTYPE_ 513 r64 : 2;
"""
#: Which forms the struct path packs (the others go through cantools).
FAST = {"BIG_ENDIAN": False, "BIT_PACKED": False, "INT24": False, "REAL32": True,
        "REAL64": True, "OFFSET": True, "PADDED": True, "INT64": True}


@pytest.fixture(scope="module")
def forms(tmp_path_factory) -> tuple[Path, cantools.database.Database]:
    path = tmp_path_factory.mktemp("forms") / "forms.dbc"
    path.write_text(FORMS)
    return path, cantools.database.load_file(str(path))


def _codec(path: Path, name: str) -> MessageCodec:
    m = parse_dbc(path)[0][name]
    return MessageCodec(m.name, m.frame_id, m.signals, m.length)


def _random_raw(sig, rng: random.Random) -> int | float:
    """A raw value of cantools signal ``sig`` (floats: moderate, so that an offset does
    not swallow them)."""
    if sig.is_float:
        x = rng.uniform(-1e6, 1e6)
        return struct.unpack("<f", struct.pack("<f", x))[0] if sig.length == 32 else x
    lo = -(1 << (sig.length - 1)) if sig.is_signed else 0
    return rng.randint(lo, lo + (1 << sig.length) - 1)


@pytest.mark.parametrize("name", list(FAST))
def test_each_form_matches_cantools_bit_for_bit(forms, name) -> None:
    path, db = forms
    codec, msg = _codec(path, name), db.get_message_by_name(name)
    assert codec.fast is FAST[name] and codec.length == msg.length
    rng = random.Random(name)
    for _ in range(400):
        data = msg.encode({s.name: _random_raw(s, rng) for s in msg.signals}, scaling=False)
        mine = codec.decode(data)
        assert mine == msg.decode(data, decode_choices=False)
        assert codec.encode(mine) == data == msg.encode(mine)
        assert codec.pack(*codec.decode_raw(data)) == data
    for _ in range(400):  # physical values between the steps: rounded alike
        values = {s.name: s.conversion.raw_to_scaled(_random_raw(s, rng))
                  + (0.3 * s.scale if not s.is_float else 0.0) for s in msg.signals}
        if name == "INT64":
            values = {"i64": rng.randint(-(1 << 63), (1 << 63) - 1)}
        try:
            expected = msg.encode(values)
        except cantools.database.EncodeError:  # +0.3 step beyond the top: cantools refuses
            continue
        assert codec.encode(values) == expected


def test_the_forms_dbc_skips_service_messages(forms) -> None:
    path, _ = forms
    messages, specs = parse_dbc(path)
    assert set(messages) == set(FAST) and "sdo_index" not in specs


def _twins(*specs: SignalSpec) -> tuple[MessageCodec, MessageCodec]:
    """The same signals packed by struct (byte-aligned little-endian) and by cantools
    (Motorola, one after the other from byte 0)."""
    fast = MessageCodec("FAST", 0x181, specs)
    starts, bit = [], 0
    for s in specs:
        starts.append(bit + 7)  # Motorola start: the most significant bit of the first byte
        bit += s.bits
    slow = MessageCodec("SLOW", 0x181, [SignalSpec(s.name, s.factor, s.bits, s.signed, s.offset,
                                                   s.is_float, st, True)
                                        for s, st in zip(specs, starts, strict=True)])
    assert fast.fast and not slow.fast
    return fast, slow


EDGES = [0.0, 0.0005, 0.0015, -0.0005, -0.0025, 1.23449999, 32.7674, 32.7675, 1e9, -1e9,
         math.inf, -math.inf, -32.7685, 65.535, 0.1 + 0.2]


def test_saturation_rounding_and_wrap_equal_the_fast_paths() -> None:
    fast, slow = _twins(SignalSpec("i_sa", 0.001, 16, True), SignalSpec("u_dc", 0.02, 16, False),
                        SignalSpec("eps_0", 2 * math.pi / 65536, 16, False),
                        SignalSpec("statusword", 1.0, 16, False))
    for x in EDGES:
        values = {"i_sa": x, "u_dc": x * 20, "eps_0": x * 3, "statusword": 0x237}
        if math.isinf(x):
            values["eps_0"] = 1.0  # an angle is finite
        assert slow.raw(values) == fast.raw(values)
        assert slow.decode(slow.encode(values)) == fast.decode(fast.encode(values))
    q = slow.phys(slow.raw({"i_sa": 1e9, "u_dc": -5.0, "eps_0": -1e-4, "statusword": 7}))
    assert q["i_sa"] == pytest.approx(32.767) and q["u_dc"] == 0.0
    assert q["eps_0"] == pytest.approx(2 * math.pi - 2 * math.pi / 65536)
    assert isinstance(q["statusword"], int)
    for codec in (fast, slow):
        with pytest.raises(ValueError):
            codec.encode({"i_sa": math.nan, "u_dc": 0.0, "eps_0": 0.0, "statusword": 0})
        with pytest.raises(KeyError):
            codec.encode({})


def test_odd_sizes_saturate_and_wrap_at_their_own_range() -> None:
    c = MessageCodec("ODD", 0x181, [SignalSpec("i24", 0.001, 24, True),
                                    SignalSpec("eps_0", 2 * math.pi / 4096, 12, False),
                                    SignalSpec("w_0", 0.5, 12, True, offset=10.0),
                                    SignalSpec("T_L", 1.0, 12, True)])
    assert not c.fast and c.length == 8
    raw = c.raw({"i24": 1e9, "eps_0": 2 * math.pi + 3 * 2 * math.pi / 4096, "w_0": -1e9,
                 "T_L": 2047.5})
    assert raw == ((1 << 23) - 1, 3, -2048, 2048 - 1)
    assert c.raw({"i24": -0.0015, "eps_0": 0.0, "w_0": 10.75, "T_L": 2.5})[::2] == (-2, 2)
    # a signed wrapping signal wraps into its range, not onto its magnitude
    w = MessageCodec("W", 0x181, [SignalSpec("eps_0", 1.0, 12, True)])
    assert w.raw({"eps_0": 2048}) == (-2048,) and w.raw({"eps_0": -2049}) == (2047,)


def test_real32_rounds_to_the_nearest_float_and_saturates() -> None:
    fast, slow = _twins(SignalSpec("w_m", 1.0, 32, True, is_float=True),
                        SignalSpec("T_e", 0.5, 64, True, offset=1.0, is_float=True))
    f32_max = struct.unpack("<f", b"\xff\xff\x7f\x7f")[0]
    for codec in (fast, slow):
        q = codec.phys(codec.raw({"w_m": 0.1, "T_e": 0.1}))
        assert q["w_m"] == struct.unpack("<f", struct.pack("<f", 0.1))[0] != 0.1
        assert q["T_e"] == pytest.approx(0.1, abs=1e-15)
        assert codec.raw({"w_m": 1e39, "T_e": math.inf}) == (f32_max, 1.7976931348623157e308)
        assert codec.raw({"w_m": -math.inf, "T_e": 0.0})[0] == -f32_max
        assert codec.decode(codec.encode({"w_m": 3.5e38, "T_e": 2.0}))["w_m"] == f32_max
        with pytest.raises(ValueError, match="NaN"):
            codec.encode({"w_m": math.nan, "T_e": 0.0})


def test_64_bit_integers_stay_exact() -> None:
    c = MessageCodec("Q", 0x181, [SignalSpec("count", 1.0, 64, True)])
    big = (1 << 62) + 1
    assert c.decode(c.encode({"count": big})) == {"count": big}
    assert c.raw({"count": 1 << 70}) == ((1 << 63) - 1,)


def test_padding_is_zero_and_a_wrong_length_is_refused(forms) -> None:
    path, _ = forms
    c = _codec(path, "PADDED")
    data = c.encode({"pad_a": -0.001, "pad_b": 255})
    assert data == bytes([0, 0xFF, 0xFF, 0, 0, 0xFF, 0, 0])
    slow = _codec(path, "BIG_ENDIAN")
    for codec in (c, slow):
        with pytest.raises(struct.error):
            codec.decode(bytes(codec.length - 1))
        with pytest.raises(struct.error):
            codec.decode_raw(bytes(codec.length + 1))


def test_the_built_in_dbc_stays_on_the_struct_path() -> None:
    codec = load_codec(1)
    assert all(c.fast for c in codec.messages.values())
    assert codec.messages["TPDO1"].pack(0x237, -1, 2, 3) == struct.pack("<HhhB", 0x237, -1, 2, 3)


# ------------------------------------------------------------------- a drive profile

#: A drive whose DBC uses the forms: Motorola currents, a REAL32 speed, a 24-bit voltage
#: with an offset, a padded RPDO and a bit-packed frame speed.
DRIVE_DBC = HEADER + """BO_ 513 RX1: 8 GATEWAY
 SG_ controlword : 0|16@1+ (1,0) [0|65535] "" DRIVE
 SG_ eps_0 : 16|16@1+ (9.587379924285257e-05,0) [0|6.283089] "rad" DRIVE
 SG_ w_0 : 32|20@1- (0.001,0) [0|0] "rad/s" DRIVE

BO_ 769 RX2: 8 GATEWAY
 SG_ i_sd_ref : 7|16@0- (0.001,0) [0|0] "A" DRIVE
 SG_ i_sq_ref : 23|16@0- (0.001,0) [0|0] "A" DRIVE
 SG_ u_sd_ref : 32|12@1- (0.5,0) [0|0] "V" DRIVE
 SG_ u_sq_ref : 44|12@1- (0.5,0) [0|0] "V" DRIVE

BO_ 385 TX1: 8 DRIVE
 SG_ statusword : 0|16@1+ (1,0) [0|65535] "" GATEWAY
 SG_ Ia : 23|16@0- (0.002,0) [0|0] "A" GATEWAY
 SG_ Ib : 39|16@0- (0.002,0) [0|0] "A" GATEWAY

BO_ 641 TX2: 8 DRIVE
 SG_ Ua : 0|24@1- (0.001,0) [0|0] "V" GATEWAY
 SG_ Ub : 24|24@1- (0.001,0) [0|0] "V" GATEWAY
 SG_ Udc : 48|16@1+ (0.05,-100) [0|0] "V" GATEWAY

BO_ 897 TX3: 4 DRIVE
 SG_ speed : 0|32@1- (1,0) [0|0] "rad/s" GATEWAY


SIG_VALTYPE_ 897 speed : 1;
"""
DRIVE_TOML = """[drive]
name = "forms drive"
eds = "builtin:drive.eds"
dbc = "forms_drive.dbc"
node = 1
[pdo]
control = "RX1"
setpoints = "RX2"
currents = "TX1"
voltages = "TX2"
truth = "TX3"
remap = false
[signals]
i_sa = "TX1.Ia"
i_sb = "TX1.Ib"
u_sa = "TX2.Ua"
u_sb = "TX2.Ub"
u_dc = "TX2.Udc"
w_m = "TX3.speed"
"""


def _drive(tmp_path: Path, dbc_text: str = DRIVE_DBC) -> Path:
    (tmp_path / "forms_drive.dbc").write_text(dbc_text)
    path = tmp_path / "forms_drive.toml"
    path.write_text(DRIVE_TOML)
    return path


def test_a_drive_profile_with_these_forms_loads_and_runs_its_process_data(tmp_path) -> None:
    path = _drive(tmp_path)
    profile = load_drive_profile(path)
    pd = process_data(profile)
    assert pd.roles >= {"i_sa", "u_dc", "w_m", "i_sd_ref", "eps_0", "w_0"}
    db = cantools.database.load_file(str(tmp_path / "forms_drive.dbc"))
    # gateway → drive: the frames the gateway would send are cantools' encoding
    values = {"controlword": 0x0F, "eps_0": 1.0, "w_0": -123.4567, "i_sd_ref": 2.5,
              "i_sq_ref": -40.0, "u_sd_ref": 100.26, "u_sq_ref": -3000.0}
    sent = {name: data for _, name, data in pd.encode(values)}
    assert {n: len(d) for n, d in sent.items()} == {"RX1": 8, "RX2": 8}
    q = pd.quantize(values, tx=False)
    for name, data in sent.items():
        assert db.get_message_by_name(name).decode(data, decode_choices=False) == {
            k: q[k] for k in db.get_message_by_name(name).signal_tree}
    assert q["i_sq_ref"] == pytest.approx(-32.768) and q["u_sq_ref"] == -1024.0  # saturated
    assert q["w_0"] == pytest.approx(-123.457) and q["u_sd_ref"] == 100.5
    # drive → gateway: cantools-encoded TPDOs decode by role, as the bus log decoder does
    tx = {"TX1": {"statusword": 0x237, "Ia": 1.234, "Ib": -0.5},
          "TX2": {"Ua": 230.001, "Ub": -229.999, "Udc": 560.05}, "TX3": {"speed": 150.25}}
    frames = [can.Message(arbitration_id=db.get_message_by_name(n).frame_id,
                          data=db.encode_message(n, v), is_extended_id=False)
              for n, v in tx.items()]
    rows = {r["name"]: r for r in decode_frames(frames, drive=profile)}
    assert rows["TX1"]["i_sa"] == pytest.approx(1.234) and rows["TX1"]["i_sb"] == -0.5
    assert rows["TX1"]["statusword"] == 0x237
    assert rows["TX2"]["u_sa"] == pytest.approx(230.001)
    assert rows["TX2"]["u_dc"] == pytest.approx(560.05)
    assert rows["TX3"]["w_m"] == 150.25
    for f in frames:
        pdo = pd.by_cob_id[f.arbitration_id]
        expected = db.decode_message(f.arbitration_id, f.data, decode_choices=False)
        assert pdo.codec.decode(f.data) == {role: expected[sig] for sig, role in pdo.signals}


# ------------------------------------------------------------------------ refusals

#: (what, DBC message, words of the refusal)
REFUSALS: list[tuple[str, str, str]] = [
    ("multiplexed", 'BO_ 385 TX1: 8 DRIVE\n SG_ sel M : 0|8@1+ (1,0) [0|0] "" GATEWAY\n'
     ' SG_ a m0 : 8|16@1- (1,0) [0|0] "" GATEWAY\n SG_ b m1 : 8|16@1- (1,0) [0|0] "" GATEWAY\n',
     "message TX1 is multiplexed (signal sel)"),
    ("longer than 64 bits", 'BO_ 385 TX1: 16 DRIVE\n SG_ big : 0|72@1+ (1,0) [0|0] "" GATEWAY\n',
     "signal big is 72 bits; a signal is at most 64 bits"),
    ("longer than 8 bytes", 'BO_ 385 TX1: 12 DRIVE\n SG_ a : 0|16@1+ (1,0) [0|0] "" GATEWAY\n',
     "message TX1 is 12 bytes; a CANopen PDO on classical CAN has at most 8"),
    ("a 16-bit float", 'BO_ 385 TX1: 8 DRIVE\n SG_ h : 0|16@1- (1,0) [0|0] "" GATEWAY\n\n'
     "SIG_VALTYPE_ 385 h : 1;\n", "signal h is a 16-bit float; a float signal is a REAL32"),
    ("an extended id", 'BO_ 2147484033 TX1: 8 DRIVE\n SG_ a : 0|16@1+ (1,0) [0|0] "" GATEWAY\n',
     "message TX1 has an extended (29-bit) id 0x181"),
    ("factor 0", 'BO_ 385 TX1: 8 DRIVE\n SG_ a : 0|16@1+ (0,0) [0|0] "" GATEWAY\n',
     "signal a has the scaling (0,0); give a finite, non-zero factor"),
    ("one name, two encodings", 'BO_ 385 TX1: 2 DRIVE\n SG_ a : 0|16@1+ (1,0) [0|0] "" GATEWAY\n'
     '\nBO_ 641 TX2: 2 DRIVE\n SG_ a : 0|16@1- (1,0) [0|0] "" GATEWAY\n',
     "signal a is defined twice, differently"),
]


@pytest.mark.parametrize("what, body, words", REFUSALS, ids=[r[0] for r in REFUSALS])
def test_what_the_codec_cannot_take_is_refused_by_name(tmp_path, what, body, words) -> None:
    path = tmp_path / "bad.dbc"
    path.write_text(HEADER + body)
    with pytest.raises(ValueError) as err:
        parse_dbc(path)
    assert str(err.value).startswith(f"{path}: ") and words in str(err.value), str(err.value)


def test_a_refused_dbc_in_a_drive_profile_is_one_paragraph(tmp_path, capsys) -> None:
    path = _drive(tmp_path, DRIVE_DBC.replace(" SG_ speed : 0|32@1- (1,0)",
                                              " SG_ speed : 0|16@1- (1,0)"))
    with pytest.raises(UserError, match="signal speed is a 16-bit float"):
        process_data(load_drive_profile(path))
    rc = main(["log", "-i", "virtual", "-c", "forms-refused", "-o", str(tmp_path / "x.blf"),
               "--drive", str(path), "--decode", "--duration", "0.1s"])
    err = capsys.readouterr().err
    assert rc == 2 and "signal speed is a 16-bit float" in err and "Traceback" not in err
    assert err.strip().count("\n") == 0, err
