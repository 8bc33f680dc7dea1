"""Reference profiles (gateway/reference/): smoothness, the paper's scenario, TOML
loading and its error messages, and the demand estimate."""

from __future__ import annotations

import dataclasses
import itertools
import math
import re
from pathlib import Path

import numpy as np
import pytest

from dbc.motor import MotorParams
from gateway.reference import (
    Profile,
    ProfileError,
    References,
    Signal,
    Step,
    demand,
    demand_trace,
    load_profile,
    paper_profile,
    parse_profile,
)

PROFILES = Path(__file__).resolve().parent.parent / "gateway" / "profiles"
SHIPPED = sorted(PROFILES.glob("*.toml"))
SIGNALS = ("speed", "flux", "load")


def _transition_times(p: Profile, name: str) -> list[tuple[float, float]]:
    return [(s.t, s.end) for s in getattr(p, name).steps]


# ------------------------------------------------------------------------ smoothness


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
@pytest.mark.parametrize("name", SIGNALS)
def test_derivatives_match_central_differences(path: Path, name: str) -> None:
    """ẋ and ẍ of every signal equal central differences of x and ẋ inside every ramp."""
    sig: Signal = getattr(load_profile(path), name)
    assert sig.steps or name == "load"
    for t0, t1 in _transition_times(load_profile(path), name):
        ramp = t1 - t0
        h = ramp * 1e-4
        scale = abs(sig.steps[0].value - sig.initial) + max(abs(v) for v in sig.values())
        for frac in np.linspace(0.013, 0.987, 37):
            t = t0 + frac * ramp
            x, dx, ddx = sig.at(t)
            xp, dxp, _ = sig.at(t + h)
            xm, dxm, _ = sig.at(t - h)
            # Errors: O(h²·x‴) for the first, O(h²·x⁗) for the second derivative.
            assert dx == pytest.approx((xp - xm) / (2 * h), rel=1e-6, abs=1e-6 * scale / ramp)
            assert ddx == pytest.approx((dxp - dxm) / (2 * h), rel=1e-6,
                                        abs=1e-6 * scale / ramp**2)
            assert ddx == pytest.approx((xp - 2 * x + xm) / h**2, rel=1e-3,
                                        abs=1e-3 * scale / ramp**2)


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
@pytest.mark.parametrize("name", SIGNALS)
def test_c2_continuity_at_ramp_ends(path: Path, name: str) -> None:
    """Value, ẋ and ẍ are continuous at the start and end of every transition: C²."""
    sig: Signal = getattr(load_profile(path), name)
    for t0, t1 in _transition_times(load_profile(path), name):
        ramp = t1 - t0
        eps = ramp * 1e-6
        for edge in (t0, t1):
            before, at, after = sig.at(edge - eps), sig.at(edge), sig.at(edge + eps)
            # derivatives at the ends are exactly zero (quintic smoothstep)
            assert at[1] == 0.0 and at[2] == 0.0
            vals = sig.values()
            span = max(abs(b - a) for a, b in itertools.pairwise(vals)) + 1.0
            for k, tol in ((0, 1e-9 * span), (1, 1e-9 * span / ramp),
                           (2, 1e-4 * span / ramp**2)):
                assert abs(before[k] - at[k]) <= tol
                assert abs(after[k] - at[k]) <= tol


def test_peak_derivatives_are_the_quintic_ones() -> None:
    """Mid-ramp slope 15/8·Δ/ramp and peak ẍ 10/√3·Δ/ramp² (at s = ½ ∓ √3/6)."""
    sig = Signal(1.0, (Step(2.0, 3.0, 0.5),))
    assert sig.at(2.25) == pytest.approx((2.0, 1.875 * 2.0 / 0.5, 0.0), abs=1e-12)
    s = 0.5 - math.sqrt(3.0) / 6.0
    assert sig.at(2.0 + s * 0.5)[2] == pytest.approx(10.0 / math.sqrt(3.0) * 2.0 / 0.25)


def test_sample_equals_at() -> None:
    p = paper_profile()
    t = np.concatenate([np.linspace(-0.1, 2.7, 3001), [0.0, 0.32, 0.5, 0.51, 1.8, 2.5]])
    s = p.sample(t)
    assert set(s) == {f.name for f in dataclasses.fields(References)}
    for i in range(0, t.size, 7):
        r = p.at(float(t[i]))
        for key, arr in s.items():
            assert arr[i] == pytest.approx(getattr(r, key), rel=1e-12, abs=1e-9), (key, t[i])


def test_references_type_and_hold_outside_the_run() -> None:
    p = paper_profile()
    r = p.at(0.41)
    assert isinstance(r, References)
    assert r == References(*(getattr(r, f.name) for f in dataclasses.fields(References)))
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.w_ref = 1.0  # type: ignore[misc]
    assert p.at(-1.0) == References(0.0, 0.0, 0.0, 0.001, 0.0, 0.0, 0.0, 0.0)
    assert p.at(10.0) == References(200.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.5, 0.0)


# --------------------------------------------------------------------- paper profile


@pytest.mark.parametrize(("t", "key", "value"), [
    (0.0, "psi_ref", 0.001), (0.4, "psi_ref", 1.16), (0.3, "w_ref", 0.0),
    (0.32, "w_ref", 0.0), (1.0, "w_ref", 100.0), (2.4, "w_ref", 200.0),
    (2.4, "psi_ref", 0.5), (0.7, "T_L", 5.8), (1.2, "T_L", 0.5), (0.49, "T_L", 0.0),
    (1.49, "psi_ref", 1.16), (1.49, "w_ref", 100.0), (2.5, "T_L", 0.5),
])
def test_paper_values_at_key_times(t: float, key: str, value: float) -> None:
    assert getattr(paper_profile().at(t), key) == pytest.approx(value, rel=1e-12, abs=1e-12)


def test_paper_profile_follows_section_6() -> None:
    p = paper_profile()
    assert p.name == "paper" and p.duration == 2.5 and p.source == "<embedded>"
    t = np.linspace(0.0, 2.5, 25001)
    s = p.sample(t)
    assert s["psi_ref"].min() >= 0.001 > 0.0
    # flux at its rated value before the speed moves; speed zero until 0.32 s
    assert np.all(s["w_ref"][t <= 0.32] == 0.0)
    assert np.all(s["psi_ref"][(t >= 0.3) & (t <= 1.5)] == pytest.approx(1.16))
    # field weakening and the second speed ramp both start at 1.5 s
    assert p.at(1.5 + 1e-3).dw_ref > 0 and p.at(1.5 + 1e-3).dpsi_ref < 0
    # dT_L/dt is finite (C² load ramps) and nonzero only around 0.5 s and 1 s
    moving = t[np.abs(s["dT_L"]) > 0]
    assert moving.size and np.all(((moving > 0.5) & (moving < 0.51))
                                  | ((moving > 1.0) & (moving < 1.01)))


def test_embedded_profile_equals_the_file() -> None:
    from_file = load_profile(PROFILES / "paper.toml")
    assert from_file == paper_profile()
    assert from_file.source.endswith("paper.toml")
    link = PROFILES.parent.parent / "profiles" / "paper.toml"  # the repository's symlink
    assert load_profile(link) == paper_profile()


def test_set_points_list_every_transition() -> None:
    sp = paper_profile().set_points()
    moves = [(x.signal, x.t_start, x.t_end, x.start, x.end) for x in sp if not x.initial]
    assert moves == [
        ("flux", 0.0, 0.3, 0.001, 1.16), ("speed", 0.32, 0.5, 0.0, 100.0),
        ("load", 0.5, 0.51, 0.0, 5.8), ("load", 1.0, 1.01, 5.8, 0.5),
        ("speed", 1.5, 1.8, 100.0, 200.0), ("flux", 1.5, 1.8, 1.16, 0.5),
    ]
    assert "0.32–0.5 s" in str(sp[4]) and "100 rad/s" in str(sp[4])


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_shipped_profiles_load_and_keep_flux_positive(path: Path) -> None:
    p = load_profile(path)
    t = np.linspace(0.0, p.duration, 5001)
    assert p.sample(t)["psi_ref"].min() > 0.0
    assert p.description


# ------------------------------------------------------------------------------ units


def _write(tmp_path: Path, text: str, name: str = "x.toml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


SI_TEXT = """
[units]
time = "s"
speed = "rad/s"
flux = "Wb"
torque = "N*m"
[profile]
name = "si"
duration = 1.0
[speed]
initial = 0.0
steps = [{ t = 0.32, value = 104.71975511965977, ramp = 0.18 }]
[flux]
initial = 0.0005
steps = [{ t = 0.0, value = 0.9, ramp = 0.25 }]
[load]
initial = 1.5
steps = [{ t = 0.6, value = 2.0, ramp = 0.02 }]
"""

SCALED_TEXT = """
[units]
time = "ms"
speed = "rpm"
flux = "mWb"
torque = "{torque}"
[profile]
name = "scaled"
duration = 1000
[speed]
initial = 0
steps = [{{ t = 320, value = 1000, ramp = 180 }}]
[flux]
initial = 0.5
steps = [{{ t = 0, value = 900, ramp = 250 }}]
[load]
initial = 1.5
steps = [{{ t = 600, value = 2, ramp = 20 }}]
"""


@pytest.mark.parametrize("torque", ["N*m", "N·m", "Nm"])
def test_unit_conversion(tmp_path: Path, torque: str) -> None:
    si = load_profile(_write(tmp_path, SI_TEXT, "si.toml"))
    sc = load_profile(_write(tmp_path, SCALED_TEXT.format(torque=torque), "scaled.toml"))
    assert sc.duration == pytest.approx(1.0)
    assert sc.speed.steps[0].value == pytest.approx(1000 * 2 * math.pi / 60)
    assert sc.speed.steps[0].t == pytest.approx(0.32) and sc.speed.steps[0].ramp == 0.18
    assert sc.flux.initial == pytest.approx(0.0005) and sc.flux.final == pytest.approx(0.9)
    for t in np.linspace(0.0, 1.0, 101):
        a, b = si.at(float(t)), sc.at(float(t))
        for f in dataclasses.fields(References):
            assert getattr(b, f.name) == pytest.approx(getattr(a, f.name), rel=1e-9,
                                                       abs=1e-9), (t, f.name)


def test_load_section_is_optional(tmp_path: Path) -> None:
    text = SI_TEXT.split("[load]")[0].replace('torque = "N*m"\n', "")
    p = load_profile(_write(tmp_path, text))
    assert p.load == Signal(0.0)
    assert p.at(0.7).T_L == 0.0 and p.at(0.7).dT_L == 0.0


# ------------------------------------------------------------------------ bad input


def _edit(old: str, new: str) -> str:
    assert old in SI_TEXT
    return SI_TEXT.replace(old, new, 1)


BAD = {
    "flux step <= 0": (
        _edit("steps = [{ t = 0.0, value = 0.9, ramp = 0.25 }]",
              "steps = [{ t = 0.0, value = 0.9, ramp = 0.25 }, "
              "{ t = 0.5, value = -0.2, ramp = 0.1 }]"),
        ["[flux].steps[1].value = -0.2", "> 0", "(15)"]),
    "flux initial zero": (_edit("initial = 0.0005", "initial = 0.0"),
                          ["[flux].initial = 0.0", "> 0"]),
    "overlapping ramps": (
        _edit("steps = [{ t = 0.32, value = 104.71975511965977, ramp = 0.18 }]",
              "steps = [{ t = 0.32, value = 100, ramp = 0.18 }, { t = 0.4, value = 50, "
              "ramp = 0.1 }]"),
        ["[speed].steps[1].t = 0.4", "previous", "0.5"]),
    "times not increasing": (
        _edit("steps = [{ t = 0.32, value = 104.71975511965977, ramp = 0.18 }]",
              "steps = [{ t = 0.32, value = 100, ramp = 0.18 }, { t = 0.1, value = 50, "
              "ramp = 0.1 }]"),
        ["[speed].steps[1].t = 0.1", "increase"]),
    "negative ramp": (_edit("ramp = 0.02", "ramp = -0.02"),
                      ["[load].steps[0].ramp = -0.02", "> 0"]),
    "zero ramp": (_edit("ramp = 0.02", "ramp = 0"), ["[load].steps[0].ramp = 0", "C²"]),
    "negative duration": (_edit("duration = 1.0", "duration = -1.0"),
                          ["[profile].duration = -1.0", "> 0"]),
    "missing duration": (_edit("duration = 1.0", ""), ["[profile].duration", "missing"]),
    "ramp past the end": (_edit("duration = 1.0", "duration = 0.61"),
                          ["[load].steps[0]", "duration"]),
    "negative step time": (_edit("t = 0.0, value = 0.9", "t = -0.1, value = 0.9"),
                           ["[flux].steps[0].t = -0.1", "≥ 0"]),
    "unknown step key": (_edit("ramp = 0.18", "rmap = 0.18"), ["[speed].steps[0].rmap",
                                                              "unknown", "ramp"]),
    "missing step key": (_edit(", ramp = 0.18", ""), ["[speed].steps[0].ramp", "missing"]),
    "unknown section key": (_edit("initial = 1.5", "initial = 1.5\nfinal = 2"),
                            ["[load].final", "unknown", "initial, steps"]),
    "unknown table": (SI_TEXT + "\n[sped]\ninitial = 1\n", ["[sped]", "unknown table"]),
    "unknown profile key": (_edit('name = "si"', 'name = "si"\nlength = 2'),
                            ["[profile].length", "unknown"]),
    "unknown units key": (_edit('time = "s"', 'time = "s"\nangle = "rad"'),
                          ["[units].angle", "unknown"]),
    "missing units": (SI_TEXT.replace('[units]\ntime = "s"\nspeed = "rad/s"\nflux = "Wb"\n'
                                      'torque = "N*m"\n', ""),
                      ["[units]", "missing section"]),
    "missing unit": (_edit('flux = "Wb"\n', ""), ["[units].flux", "missing", "mWb"]),
    "unknown unit": (_edit('speed = "rad/s"', 'speed = "krpm"'),
                     ["[units].speed = 'krpm'", "rpm"]),
    "unit not a string": (_edit('time = "s"', "time = 1"), ["[units].time = 1", "unknown unit"]),
    "value is a string": (_edit("value = 104.71975511965977", 'value = "100"'),
                          ["[speed].steps[0].value = '100'", "number"]),
    "value is a bool": (_edit("initial = 1.5", "initial = true"),
                        ["[load].initial = True", "number"]),
    "value is nan": (_edit("initial = 1.5", "initial = nan"), ["[load].initial", "finite"]),
    "steps not an array": (_edit("steps = [{ t = 0.6, value = 2.0, ramp = 0.02 }]",
                                 "steps = 3"), ["[load].steps = 3", "array of tables"]),
    "step not a table": (_edit("steps = [{ t = 0.6, value = 2.0, ramp = 0.02 }]",
                               "steps = [0.6]"), ["[load].steps[0] = 0.6", "table"]),
    "section not a table": ("load = 2\n" + SI_TEXT.split("[load]")[0],
                            ["load = 2", "[load] section"]),
    "missing flux": (SI_TEXT.replace("[flux]\ninitial = 0.0005\nsteps = [{ t = 0.0, value = "
                                     "0.9, ramp = 0.25 }]\n", ""),
                     ["[flux]", "missing section"]),
    "missing speed initial": (_edit("[speed]\ninitial = 0.0", "[speed]"),
                              ["[speed].initial", "missing"]),
    "name not a string": (_edit('name = "si"', "name = 3"), ["[profile].name = 3", "string"]),
    "TOML syntax": (_edit("duration = 1.0", "duration = = 1.0"), ["not valid TOML", "line 9"]),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_profiles_name_file_and_key(tmp_path: Path, case: str) -> None:
    text, expected = BAD[case]
    path = _write(tmp_path, text, "bad.toml")
    with pytest.raises(ProfileError) as info:
        load_profile(path)
    msg = str(info.value)
    assert isinstance(info.value, ValueError)
    assert msg.startswith(f"{path}: "), msg
    for part in expected:
        assert part in msg, (part, msg)
    assert info.value.__cause__ is None or isinstance(info.value.__cause__, Exception)


def test_missing_file_names_the_path(tmp_path: Path) -> None:
    path = tmp_path / "nope.toml"
    with pytest.raises(ProfileError, match=r"nope\.toml: no such file"):
        load_profile(path)


def test_not_utf8(tmp_path: Path) -> None:
    path = tmp_path / "latin.toml"
    path.write_bytes(b"# \xff\n")
    with pytest.raises(ProfileError, match="UTF-8"):
        load_profile(path)


def test_parse_profile_names_the_source() -> None:
    with pytest.raises(ProfileError, match=r"^<mine>: \[flux\]"):
        parse_profile(SI_TEXT.replace("value = 0.9", "value = 0"), "<mine>")


def test_programmatic_construction_is_checked() -> None:
    good = Signal(1.0, (Step(0.0, 2.0, 0.1),))
    with pytest.raises(ProfileError, match=r"> 0"):
        Profile("p", 1.0, speed=good, flux=Signal(1.0, (Step(0.0, -1.0, 0.1),)))
    with pytest.raises(ProfileError, match="duration"):
        Profile("p", 0.0, speed=good, flux=good)
    with pytest.raises(ProfileError, match="ramp"):
        Signal(1.0, (Step(0.0, 2.0, 0.0),))
    with pytest.raises(ProfileError, match="before the previous"):
        Signal(1.0, (Step(0.0, 2.0, 0.2), Step(0.1, 3.0, 0.1)))


# ------------------------------------------------------- limits: what cannot run is refused

ROOT = Path(__file__).resolve().parent.parent


def _limited(speed: float | str, flux: float = 1.16, load: float = 2.0,
             speed_unit: str = "rad/s") -> str:
    """A profile with one speed, flux and load set point each."""
    return SI_TEXT.replace('speed = "rad/s"', f'speed = "{speed_unit}"').replace(
        "value = 104.71975511965977", f"value = {speed}").replace(
        "value = 0.9", f"value = {flux}").replace("value = 2.0", f"value = {load}")


def _cli(*args: str) -> tuple[int, str, str]:
    """``hil-gateway ARGS`` in a subprocess, as a user runs it: (status, stdout, stderr)."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "gateway", *args], capture_output=True,
                       text=True, cwd=ROOT, timeout=120)
    return r.returncode, r.stdout, r.stderr


def _refusal(capsys: pytest.CaptureFixture[str], *args: str) -> str:
    """Run the CLI in this process; it must refuse with status 2 and one paragraph."""
    from gateway.cli import main

    assert main(list(args)) == 2
    out, err = capsys.readouterr()
    assert err.startswith("hil-gateway: error: ") and "Traceback" not in err, err
    assert err.strip().count("\n") == 0, err  # one paragraph
    assert "is valid" not in out
    return err


def test_limits_come_from_the_dbc_and_the_eds() -> None:
    """The ranges are the DBC's (INT16 × factor) and the over-speed limit is the EDS default,
    which is the emulated drive's w_max."""
    from dbc import signal_specs
    from gateway.reference import reference_limits
    from plant.params import DriveParams

    specs = signal_specs()
    limits = reference_limits()
    bus, overspeed = limits["speed"]
    for sig in ("w_0", "w_m"):
        assert bus.hi <= specs[sig].hi * specs[sig].factor
        assert bus.lo >= specs[sig].lo * specs[sig].factor
    assert bus.hi == pytest.approx(1024.0, abs=0.04) and bus.lo == pytest.approx(-1024.0)
    assert (overspeed.lo, overspeed.hi) == (-DriveParams().w_max, DriveParams().w_max)
    assert "0x2201:9" in overspeed.what and "drive.eds" in overspeed.what
    (flux,) = limits["flux"]
    assert flux.hi == pytest.approx(specs["psi_ra"].hi * specs["psi_ra"].factor)
    (load,) = limits["load"]
    assert load.hi == pytest.approx(specs["T_L"].hi * specs["T_L"].factor)
    assert load.lo == pytest.approx(specs["T_L"].lo * specs["T_L"].factor)


def test_a_speed_of_1e6_is_refused_naming_the_limit_and_the_file(tmp_path: Path) -> None:
    path = _write(tmp_path, _limited("1e6"), "fast.toml")
    status, out, err = _cli("reference", "check", str(path))
    assert status == 2, (out, err)
    assert out == "" and "Traceback" not in err
    assert err.startswith(f"hil-gateway: error: {path}: [speed].steps[0].value = 1000000.0: ")
    assert err.strip().count("\n") == 0, err
    assert "w_max = 600 rad/s" in err and "0x2201:9" in err  # the drive's over-speed limit
    assert "w_0 in RPDO1 and w_m in TPDO3" in err             # and the bus range
    assert "|ω*| ≤ 600 rad/s" in err                          # the fix
    with pytest.raises(ProfileError, match=r"fast\.toml: \[speed\]\.steps\[0\]\.value"):
        load_profile(path)


def test_a_speed_beyond_the_bus_range_is_refused(tmp_path: Path, capsys) -> None:
    path = _write(tmp_path, _limited(2000), "bus.toml")
    err = _refusal(capsys, "profile", "check", str(path))
    assert str(path) in err and "[speed].steps[0].value = 2000" in err
    assert "the range the bus carries it in" in err and "INT16 at 0.03125 rad/s per bit" in err
    assert "-1024 to 1023.97 rad/s" in err


def test_a_speed_beyond_the_over_speed_limit_alone_is_refused(tmp_path: Path, capsys) -> None:
    path = _write(tmp_path, _limited(-700), "over.toml")
    err = _refusal(capsys, "reference", "check", str(path))
    assert "[speed].steps[0].value = -700" in err and "w_max = 600 rad/s" in err
    assert "EMCY 0x8400" in err and "the range the bus carries" not in err


def test_limits_are_given_in_the_files_unit(tmp_path: Path, capsys) -> None:
    path = _write(tmp_path, _limited(10000, speed_unit="rpm"), "rpm.toml")
    err = _refusal(capsys, "reference", "check", str(path))
    assert "10000 rpm (1047.2 rad/s)" in err and "|ω*| ≤ 5729.58 rpm (600 rad/s)" in err


@pytest.mark.parametrize(("flux", "load", "where", "needles"), [
    (5.0, 2.0, "[flux].steps[0].value = 5.0", ["psi_ra and psi_rb in TPDO3", "ψ* ≤ 3.2767 Wb"]),
    (1.16, 400.0, "[load].steps[0].value = 400.0", ["T_L in RPDO3", "-327.68 to 327.67 N·m"]),
    (1.16, -1000.0, "[load].steps[0].value = -1000.0", ["T_L in RPDO3"]),
])
def test_flux_and_load_beyond_the_bus_range_are_refused(tmp_path: Path, capsys, flux, load,
                                                        where, needles) -> None:
    path = _write(tmp_path, _limited(100, flux=flux, load=load))
    err = _refusal(capsys, "reference", "check", str(path))
    assert f"{path}: {where}: " in err
    for needle in needles:
        assert needle in err, (needle, err)


def test_a_speed_within_the_limits_is_accepted_with_warnings(tmp_path: Path, capsys) -> None:
    """500 rad/s fits the bus and the over-speed limit: valid; its high demand is a warning."""
    from gateway.cli import main

    path = _write(tmp_path, _limited(500), "ok.toml")
    assert main(["reference", "check", str(path)]) == 0
    out = capsys.readouterr().out
    assert "is valid" in out and "0 → 500 rad/s" in out and "|ω*| ≤ 600 rad/s" in out
    assert "warning:" in out  # the voltage it would need: a warning, not a refusal
    assert load_profile(path).speed.final == 500.0


@pytest.mark.parametrize("path", sorted((ROOT / "profiles").glob("*.toml")),
                         ids=lambda p: p.stem)
def test_shipped_profiles_pass_the_check(path: Path, capsys) -> None:
    from gateway.cli import main

    assert main(["reference", "check", str(path)]) == 0
    assert "is valid" in capsys.readouterr().out


@pytest.mark.parametrize("command", ["simulate", "sim"])
def test_a_run_is_refused_before_anything_runs(tmp_path: Path, capsys, command) -> None:
    path = _write(tmp_path, _limited("1e6"), "fast.toml")
    out = tmp_path / "run"
    err = _refusal(capsys, command, "--reference", str(path), "--out", str(out))
    assert f"{path}: [speed].steps[0].value" in err and "w_max = 600 rad/s" in err
    assert not out.exists()


def test_simulate_continuous_runs_a_profile_within_the_limits(tmp_path: Path, capsys) -> None:
    from gateway.cli import main

    path = _write(tmp_path, _limited(500), "ok.toml")
    out = tmp_path / "run"
    assert main(["simulate", "--period", "continuous", "--reference", str(path),
                 "--duration", "20ms", "--out", str(out)]) == 0
    assert (out / "summary.json").is_file()


def test_limits_can_be_given_or_waived() -> None:
    """A caller that knows its drive passes its own limits; ``{}`` checks none."""
    from gateway.reference import ReferenceLimit

    assert parse_profile(_limited("1e6"), limits={}).speed.final == 1e6
    tight = {"speed": (ReferenceLimit(-50.0, 50.0, "a test limit"),)}
    with pytest.raises(ProfileError, match=r"beyond a test limit; .*\|ω\*\| ≤ 50 rad/s"):
        parse_profile(_limited(100), "<t>", limits=tight)


# ---------------------------------------------------------------------------- demand

# Hand values for the paper's motor (section 6): J = 0.0075, R_s = 5.3, R_r = 3.3,
# L_s = 0.365, L_r = 0.375, M = 0.34.
ALPHA = 3.3 / 0.375                     # 8.8 s⁻¹
MU = 0.34 / (0.0075 * 0.375)            # 120.89 1/(kg·m²)
SIGMA = 0.365 - 0.34**2 / 0.375         # 0.05673 H


def test_demand_paper_steady_state_by_hand() -> None:
    """At 0.8 s: ω* = 100, ψ* = 1.16, T_L = 5.8, no derivatives."""
    d = demand_trace(paper_profile(), MotorParams())
    k = int(np.argmin(np.abs(d["t"] - 0.8)))
    i_sd = 1.16 / 0.34                                   # (9): 3.412 A
    i_sq = 5.8 / 0.0075 / (MU * 1.16)                     # (10): 5.515 A
    w_0 = 100.0 + ALPHA * 0.34 * i_sq / 1.16              # (11): 114.2 rad/s
    psi_sd = SIGMA * i_sd + 0.34 / 0.375 * 1.16
    psi_sq = SIGMA * i_sq
    u_sd = 5.3 * i_sd - w_0 * psi_sq
    u_sq = 5.3 * i_sq + w_0 * psi_sd
    assert d["i_sd"][k] == pytest.approx(i_sd, rel=1e-9)
    assert d["i_sq"][k] == pytest.approx(i_sq, rel=1e-9)
    assert d["w_0"][k] == pytest.approx(w_0, rel=1e-9)
    assert d["u_sd"][k] == pytest.approx(u_sd, rel=1e-6)
    assert d["u_sq"][k] == pytest.approx(u_sq, rel=1e-6)
    assert math.hypot(u_sd, u_sq) == pytest.approx(172.5, abs=1.0)


def test_demand_paper_voltage_during_load_ramp_by_hand() -> None:
    """At 0.505 s (middle of the 10 ms load ramp) dψ_sq/dt = σ·di_sq*/dt adds ≈ 59 V."""
    d = demand_trace(paper_profile(), MotorParams())
    k = int(np.argmin(np.abs(d["t"] - 0.505)))
    assert d["t"][k] == pytest.approx(0.505, abs=1e-9)
    T_L, dT_L = 2.9, 1.875 * 5.8 / 0.01                  # smoothstep midpoint
    i_sd = 1.16 / 0.34
    i_sq = T_L / 0.0075 / (MU * 1.16)                     # (10)
    di_sq = dT_L / 0.0075 / (MU * 1.16)
    w_0 = 100.0 + ALPHA * 0.34 * i_sq / 1.16              # (11)
    psi_sd = SIGMA * i_sd + 0.34 / 0.375 * 1.16
    u_sd = 5.3 * i_sd - w_0 * SIGMA * i_sq
    u_sq = SIGMA * di_sq + 5.3 * i_sq + w_0 * psi_sd      # ≈ 58.7 + 14.6 + 133.4 V
    assert d["u_sd"][k] == pytest.approx(u_sd, rel=1e-3)
    assert d["u_sq"][k] == pytest.approx(u_sq, rel=1e-4)
    dm = demand(paper_profile(), MotorParams())
    assert 0.5 < dm.t_u_s_peak < 0.51
    assert dm.u_s_peak == pytest.approx(math.hypot(u_sd, u_sq), rel=2e-2)


def test_demand_paper_peaks() -> None:
    dm = demand(paper_profile(), MotorParams())
    # Peak |i_s| mid speed ramp (t = 0.41 s): ω̇* = 1.875·100/0.18, i_sd = 1.16/0.34.
    i_sq = 1.875 * 100 / 0.18 / (MU * 1.16)
    assert dm.i_s_peak == pytest.approx(math.hypot(1.16 / 0.34, i_sq), rel=1e-3)
    assert 0.40 <= dm.t_i_s_peak <= 0.42
    assert dm.i_sq_peak == pytest.approx(i_sq, rel=2e-2)
    # i_sd* = ψ*/M + ψ̇*/(αM) during magnetisation: above the rated 3.41 A, below
    # 1.16/0.34 + 1.875·1.159/0.3/(αM)
    assert 1.16 / 0.34 < dm.i_sd_peak < 1.16 / 0.34 + 1.875 * 1.159 / 0.3 / (ALPHA * 0.34)
    # Voltage: above the steady 100 rad/s full-load value, below u_dc/√3 of the default drive
    assert 172.0 < dm.u_s_peak < 560.0 / math.sqrt(3.0)
    assert dm.w_peak == 200.0
    assert 200.0 < dm.w_0_peak < 230.0
    # |T_e| = J·ω̇* + T_L: peak J·1.875·100/0.18 = 7.81 N·m (no load during that ramp)
    assert dm.T_e_peak == pytest.approx(0.0075 * 1.875 * 100 / 0.18, rel=1e-3)


@dataclasses.dataclass(frozen=True)
class _StandInMotor:
    """Only the attribute names of plant.params.MotorParams that demand() uses."""

    J: float = 0.0075
    R_s: float = 5.3
    R_r: float = 3.3
    L_s: float = 0.365
    L_r: float = 0.375
    M: float = 0.34

    @property
    def alpha(self) -> float:
        return self.R_r / self.L_r

    @property
    def mu(self) -> float:
        return self.M / (self.J * self.L_r)

    @property
    def sigma(self) -> float:
        return self.L_s - self.M**2 / self.L_r


def test_demand_needs_only_the_motor_attributes() -> None:
    p = load_profile(PROFILES / "quick.toml")
    assert demand(p, _StandInMotor()) == demand(p, MotorParams())


def test_a_real_drives_run_is_not_held_to_the_emulators_limits(tmp_path: Path) -> None:
    """`run --drive OTHER.toml`: another drive's limits are its own; the emulator's
    over-speed limit (600 rad/s) does not refuse a 700 rad/s profile there, while `sim`
    (the emulator) does."""
    from dataclasses import replace

    from gateway.cli import _load_profile
    from gateway.drive_profile import load_drive_profile
    from gateway.errors import UserError

    path = _write(tmp_path, _limited("700"), "fast.toml")
    emulator = load_drive_profile(None)
    other = replace(emulator, emulator=False)
    assert _load_profile(str(path), other).speed.final == 700.0
    with pytest.raises(UserError, match="w_max"):
        _load_profile(str(path), emulator)


# ------------------------------------------------------------ drive profiles, off line


def main(argv: list[str]) -> int:
    from gateway.cli import main as cli_main

    return cli_main(argv)


def _drive_copy(tmp_path: Path, dbc_edit=None, toml_edit=None) -> Path:
    """The emulator's drive profile copied into tmp_path with its DBC, edited."""
    import gateway
    from dbc import DBC_PATH

    text = (Path(gateway.__file__).parent / "drives" / "emulator.toml").read_text()
    dbc = DBC_PATH.read_text()
    (tmp_path / "d.dbc").write_text(dbc_edit(dbc) if dbc_edit else dbc)
    text = text.replace('dbc = "builtin:drive.dbc"', 'dbc = "d.dbc"')
    path = tmp_path / "drive.toml"
    path.write_text(toml_edit(text) if toml_edit else text)
    return path


@pytest.mark.parametrize("name, runs, cannot", [
    ("emulator", ("current-loop", "voltage"), ("torque", "velocity")),
    ("emulator-standard", ("torque", "velocity"), ("current-loop", "voltage")),
])
def test_profile_check_takes_a_drive_profile(capsys, name, runs, cannot) -> None:
    """`profile check DRIVE.toml`: every signal against its EDS object, and which drive
    modes the profile can run."""
    import gateway

    path = Path(gateway.__file__).parent / "drives" / f"{name}.toml"
    assert main(["profile", "check", str(path)]) == 0
    out = capsys.readouterr().out
    assert "ERROR" not in out and out.rstrip().endswith("every signal fits its object")
    for mode in runs:
        assert re.search(rf"--drive-mode {mode}\s+runs", out), mode
    for mode in cannot:
        assert re.search(rf"--drive-mode {mode}\s+cannot run", out), mode
    assert "0x6040.0" in out  # the controlword, by index


def test_profile_check_finds_a_size_that_does_not_fit(tmp_path: Path, capsys) -> None:
    path = _drive_copy(tmp_path, dbc_edit=lambda t: t.replace(
        "BO_ 641 TPDO2: 6 DRIVE", "BO_ 641 TPDO2: 8 DRIVE").replace(
        "SG_ u_dc : 32|16@1+", "SG_ u_dc : 32|32@1+"))
    assert main(["profile", "check", str(path)]) == 1
    out = capsys.readouterr().out
    assert "ERROR: 'u_dc' is 16 bits in the EDS, the DBC signal 32" in out
    assert "not ok" in out


def test_profile_check_finds_a_signal_without_object(tmp_path: Path, capsys) -> None:
    path = _drive_copy(
        tmp_path, dbc_edit=lambda t: t.replace("SG_ T_L : 0|16@1-", "SG_ Tload : 0|16@1-"),
        toml_edit=lambda t: t + '\n[signals]\nT_L = "RPDO3.Tload"\n')
    assert main(["profile", "check", str(path)]) == 1
    out = capsys.readouterr().out
    assert "the EDS has no object named 'Tload'" in out


def test_profile_check_of_a_broken_drive_profile_is_one_paragraph(tmp_path: Path,
                                                                  capsys) -> None:
    path = _drive_copy(tmp_path, toml_edit=lambda t: t.replace('currents = "TPDO1"',
                                                               'currents = "TPDO9"'))
    assert main(["profile", "check", str(path)]) == 2
    err = capsys.readouterr().err
    assert "TPDO9" in err and "Traceback" not in err
