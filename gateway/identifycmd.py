"""`hil-gateway identify`: commission a motor like a real drive's identification run, and
write what it found as a motor file for `--motor`.

The test is the ``identify`` controller (:mod:`gateway.control.identify`: DC current steps
on one axis at standstill) run by the command the user names, with that command's own
options — ``simulate`` (the default: the plant in this process, ``--plant``), ``sim`` (the
emulator over CANopen) or ``run`` (a real drive, ``--drive``, ``-i``/``-c``) — so the drive
is identified, configured and shut down exactly as for every run. Its run directory keeps
the record; the motor file (``-o``) gets model (1)'s parameters and a ``[commissioning]``
table (sensor offsets, the phase-b sensor's gain, the inverter's voltage error, the drift
of R_s during the test), and a table is printed: each value, its standard deviation, its
verdict and the motor file it replaces (``--motor``, default the paper's motor).
"""

from __future__ import annotations

import argparse
import datetime
import math
import shlex
import tempfile
from pathlib import Path
from typing import Any

from dbc.motor import COMMISSIONING, MotorParams, ParamsError
from gateway.errors import UserError

PROG = "hil-gateway"
#: The commands the test runs through.
COMMANDS = ("simulate", "sim", "run")
#: Options the test sets itself.
_OWN = ("--controller", "--controller-params", "--reference", "--profile", "--duration",
        "--commissioning", "--no-commissioning")
#: Model (1)'s parameters in the motor file, with their units.
_MOTOR_UNITS = {"J": "kg·m²", "R_s": "Ω", "R_r": "Ω", "L_s": "H", "L_r": "H", "M": "H"}
#: What the [commissioning] table keeps, from the fit's values.
_EXTRA = {"offset_a": "A, added to the phase-a current reading",
          "offset_b": "A, phase b",
          "gain_b": "the phase-b reading's gain relative to phase a's",
          "u_dead": "V, the inverter's voltage error along a phase current's sign (dead "
                    "time: u_dead = dead_time·f_pwm·u_dc)",
          "R_s_drift": "1/s, R_s's relative change per second during the test (warming)"}

#: What the rotating test adds to the [commissioning] table.
_FRICTION = {"friction_viscous": "N·m·s, viscous friction B (rotating test)",
             "friction_coulomb": "N·m, Coulomb friction c (rotating test)"}

#: The test's reference profile: ω* = 0, no load (the test steps the current itself; the
#: flux reference only tells the divergence guard what to expect); its duration is set by
#: --duration.
STANDSTILL = """\
[units]
time = "s"
speed = "rad/s"
flux = "Wb"
torque = "N*m"

[profile]
name = "standstill"
description = "ω* = 0, no load: the standstill test of hil-gateway identify"
duration = 2.5

[flux]
initial = 0.5

[speed]
initial = 0.0

[load]
initial = 0.0
"""

DESCRIPTION = """\
Commission the motor at standstill, as a drive's identification run does: DC current steps
on one axis of the stator (+I, +2I, −I, −2I, each held --hold seconds; no torque, the rotor
does not turn) through the command --on names, with that command's own options:

  hil-gateway identify                               the plant of `simulate` (paper's motor)
  hil-gateway identify --plant real-drive            a plant scenario
  hil-gateway identify --on sim --plant rs+10        the emulator over CANopen
  hil-gateway identify --on run --drive my.toml -i socketcan -c can0   a real drive

It finds R_s, σ = L_s − M²/L_r, M²/L_r and α = R_r/L_r (so L_s, L_r, M and R_r with the
nameplate's L_r/L_s), the current sensors' offsets and relative gain, the inverter's
voltage error (dead time) and the drift of R_s, each with its standard deviation and a
verdict, prints them beside the motor file's (--motor) and writes a motor file (-o) that
--motor takes in every later run. J is measured only with --rotate (the motor turns,
within --speed and --torque; it needs the drive's speed): otherwise the nameplate's is
kept. The drive must take current setpoints (--drive-mode ideal or
current-loop) and report the applied voltages. Exit status: 0 written, 1 the test or
the fit failed (the run directory says why), 2 bad input."""


def add_parser(sub: Any) -> None:
    p = sub.add_parser("identify", help="commission the motor at standstill and write a "
                       "motor file (R_s, R_r, inductances, sensor offsets, dead time)",
                       description=DESCRIPTION, allow_abbrev=False,  # --out: the run's
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--on", dest="on", choices=COMMANDS, default="simulate",
                   help="the command the test runs through (default simulate); every other "
                        "option is that command's (--plant, --motor, --drive, -i, -c, "
                        "--period, --out, ...)")
    p.add_argument("-o", "--output", metavar="FILE.toml", default="identified-motor.toml",
                   help="the motor file to write (default ./identified-motor.toml; an "
                        "existing file is not replaced without --replace)")
    p.add_argument("--replace", action="store_true", help="replace an existing -o file")
    p.add_argument("--current", type=float, default=None, metavar="A",
                   help="the first step's current, A (default 1.5; the second is twice it)")
    p.add_argument("--hold", default=None, metavar="DURATION",
                   help="how long each step is held (default 500ms; longer averages more "
                        "sensor noise)")
    p.add_argument("--rotate", action="store_true",
                   help="then a rotating test, with the motor the standstill test found: "
                        "torque steps from rest to +SPEED, to −SPEED and back, then to rest "
                        "(field-oriented with the drive's speed sensor), for J and the "
                        "friction; the motor turns: only when it may")
    p.add_argument("--speed", type=float, default=None, metavar="RAD_S",
                   help="the rotating test's speed limit, rad/s (default 50; the test stops "
                        "its torque past 1.5× it)")
    p.add_argument("--torque", type=float, default=None, metavar="N_M",
                   help="the rotating test's torque, N·m (default 1)")
    p.set_defaults(func=cmd_identify, options=[])


def cmd_identify(args: argparse.Namespace) -> int:
    from gateway.control.identify import DEFAULTS, duration
    from gateway.units import parse_duration

    options = list(args.options)
    for word in options:
        name = word.split("=", 1)[0]
        if name in _OWN:
            raise UserError(f"identify: {name} is the test's own (it runs the identify "
                            "controller on a standstill profile); leave it out")
    params = dict(DEFAULTS)
    if args.current is not None:
        if not args.current > 0:
            raise UserError(f"--current {args.current}: give a positive current, A")
        params["current"] = args.current
    if args.hold is not None:
        params["hold"] = parse_duration(args.hold, "--hold")
        if not params["hold"] > 0:
            raise UserError(f"--hold {args.hold}: give a positive duration, e.g. 500ms")
    rotating = _rotating_params(args)
    out = Path(args.output)
    if out.suffix.lower() != ".toml":
        raise UserError(f"-o {out}: a motor file is TOML; give a name ending in .toml")
    if out.exists() and not args.replace:
        raise UserError(f"-o {out}: the file exists; give another name, or --replace")
    nameplate_file = _option(options, "--motor")
    nameplate = _nameplate(nameplate_file)
    run_dir = _option(options, "--out")
    if run_dir is None:
        stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
        run_dir = f"runs/{stamp}-identify"
        options += ["--out", run_dir]
    with tempfile.TemporaryDirectory(prefix="hil-identify-") as tmp:
        params_file = Path(tmp) / "identify.toml"
        params_file.write_text("".join(f"{k} = {v!r}\n" for k, v in params.items()))
        profile = Path(tmp) / "standstill.toml"
        profile.write_text(STANDSTILL)
        # the test measures the sensors as they read: no earlier correction around it
        argv = [args.on, *options, "--controller", "identify", "--controller-params",
                str(params_file), "--reference", str(profile), "--duration",
                f"{duration(params)}s", "--no-commissioning"]
        status = _run(argv)
    summary = _summary(Path(run_dir))
    if summary is None:
        return status or 1
    ident = summary.get("identification") or {}
    if not ident.get("ok"):
        why = ident.get("reason") or summary.get("run", {}).get("stop_reason", "")
        print(f"{PROG} identify: no result: {why} (see {run_dir})")
        return 1
    command = f"{PROG} identify --on {args.on} {shlex.join(args.options)}"
    if rotating is not None:
        rot = _rotate(args.on, options, motor_file(ident, command, run_dir), rotating,
                      run_dir)
        if not rot.get("ok"):
            print(f"{PROG} identify: the standstill test worked, the rotating one did not: "
                  f"{rot.get('reason', 'no result')} (see {run_dir}-rotating); without "
                  "--rotate the standstill values are written")
            return 1
        ident = _with_rotating(ident, rot)
    print(table(ident, nameplate, nameplate_file))
    text = motor_file(ident, command, run_dir)
    try:
        out.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise UserError(f"cannot write {out}: {exc.strerror or exc}; choose another -o") from exc
    print(f"wrote {out} (use it with --motor {out}); the run: {run_dir}")
    return 0


def _rotating_params(args: argparse.Namespace) -> dict[str, float] | None:
    """The rotating test's parameters, or None without --rotate (UserError: bad values, or
    --speed/--torque without --rotate)."""
    from gateway.control.inertia import DEFAULTS

    given = {k: v for k, v in (("speed", args.speed), ("torque", args.torque))
             if v is not None}
    if not args.rotate:
        if given:
            raise UserError(f"--{next(iter(given))} sets the rotating test: add --rotate")
        return None
    for k, v in given.items():
        if not (math.isfinite(v) and v > 0):
            unit = "rad/s" if k == "speed" else "N·m"
            raise UserError(f"--{k} {v:g}: give a positive value, {unit}")
    return {**{k: DEFAULTS[k] for k in ("speed", "torque")}, **given}


def _rotate(on: str, options: list[str], standstill_file: str, params: dict[str, float],
            run_dir: str) -> dict[str, Any]:
    """The rotating test through ``on`` with the standstill test's motor file (its
    corrections too): its summary's identification (or why there is none)."""
    from gateway.control.inertia import duration

    rot_dir = f"{run_dir}-rotating"
    rest = _without(options, ("--motor", "--out"))
    with tempfile.TemporaryDirectory(prefix="hil-identify-") as tmp:
        motor = Path(tmp) / "standstill-motor.toml"
        motor.write_text(standstill_file, encoding="utf-8")
        params_file = Path(tmp) / "rotating.toml"
        params_file.write_text("".join(f"{k} = {v!r}\n" for k, v in params.items()))
        profile = Path(tmp) / "standstill.toml"
        profile.write_text(STANDSTILL)
        seconds = duration(MotorParams.from_toml(motor), params)
        print(f"{PROG} identify: the rotating test, up to {seconds:.3g} s (the motor turns "
              f"up to ±{params['speed']:g} rad/s)")
        status = _run([on, *rest, "--motor", str(motor), "--out", rot_dir,
                       "--controller", "identify-rotating", "--controller-params",
                       str(params_file), "--reference", str(profile), "--duration",
                       f"{seconds}s"])
    summary = _summary(Path(rot_dir))
    if summary is None:
        return {"ok": False, "reason": f"the run gave no summary (exit status {status})"}
    return summary.get("identification") or {
        "ok": False, "reason": summary.get("run", {}).get("stop_reason", "")}


def _without(options: list[str], names: tuple[str, ...]) -> list[str]:
    """``options`` without ``names`` and their values (``--x V`` or ``--x=V``)."""
    out: list[str] = []
    skip = False
    for word in options:
        if skip:
            skip = False
        elif word in names:
            skip = True
        elif not word.startswith(tuple(f"{n}=" for n in names)):
            out.append(word)
    return out


def _with_rotating(ident: dict[str, Any], rot: dict[str, Any]) -> dict[str, Any]:
    """The standstill identification with the rotating test's J and friction."""
    values = {**ident["values"], **rot["values"]}
    motor = {**ident["motor"], "J": rot["values"]["J"]["value"]}
    return {**ident, "values": values, "motor": motor, "rotating": True}


def _option(options: list[str], name: str) -> str | None:
    """The value of ``name`` among ``options`` (``--x V`` or ``--x=V``), or None."""
    for k, word in enumerate(options):
        if word == name and k + 1 < len(options):
            return options[k + 1]
        if word.startswith(name + "="):
            return word.split("=", 1)[1]
    return None


def _nameplate(path: str | None) -> MotorParams:
    if path is None:
        return MotorParams.paper()
    try:
        return MotorParams.from_toml(path)
    except ParamsError as exc:
        raise UserError(str(exc)) from exc


def _run(argv: list[str]) -> int:
    """The test through the command line's own entry (its messages, its exit status)."""
    from gateway.cli import main

    return main(argv)


def _summary(run_dir: Path) -> dict[str, Any] | None:
    import json

    path = run_dir / "summary.json"
    if not path.is_file():
        return None
    return json.loads(path.read_text(encoding="utf-8"))


def table(ident: dict[str, Any], nameplate: MotorParams, source: str | None) -> str:
    """The printed table: each value, ± its standard deviation, its verdict, and the
    motor file's value it replaces."""
    motor = ident["motor"]
    values = ident["values"]
    rows = [("value", "identified", "± std", "verdict", source or "paper's motor", "change")]
    derived = {"R_s": "R_s", "R_r": "alpha", "L_s": "sigma", "L_r": "sigma", "M": "L_mu",
               "J": "J"}
    for name in ("R_s", "R_r", "L_s", "L_r", "M", "J"):
        old = getattr(nameplate, name)
        new = motor[name]
        est = values.get(derived.get(name, ""), {})
        rel_std = est.get("std", 0.0) / abs(est["value"]) if est.get("value") else 0.0
        rows.append((f"{name}, {_MOTOR_UNITS[name]}", f"{new:.5g}",
                     f"{100 * rel_std:.2g} %" if est else "—",
                     est.get("verdict", "not measured"), f"{old:.5g}",
                     f"{100 * (new / old - 1):+.1f} %"))
    for name in ("sigma", "L_mu", "alpha"):
        e = values[name]
        rows.append((f"{name}, {e['unit']}", f"{e['value']:.5g}", f"{e['std']:.2g}",
                     e["verdict"], "", ""))
    for name in (*_EXTRA, *_FRICTION):
        if name not in values:
            continue
        e = values[name]
        rows.append((f"{name}, {e['unit'] or '1'}", f"{e['value']:.4g}", f"{e['std']:.2g}",
                     e["verdict"], "", ""))
    widths = [max(len(r[c]) for r in rows) for c in range(len(rows[0]))]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(r, widths, strict=True)).rstrip()
             for r in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    kept = "L_r/L_s" if ident.get("rotating") else "J and L_r/L_s"
    lines.append(f"residual of the fit: {1e3 * ident['residual_rms_V']:.3g} mV rms over "
                 f"{ident['samples']} samples; {kept}: the motor file's (not measured "
                 "at standstill)")
    return "\n".join(lines)


def motor_file(ident: dict[str, Any], command: str, run_dir: str) -> str:
    """The motor file's text: model (1)'s parameters at the top level (the format of
    gateway/motors/paper.toml), the rest in [commissioning]."""
    motor, values = ident["motor"], ident["values"]
    rotating = bool(ident.get("rotating"))
    notes = {"J": ("measured by the rotating test" if rotating
                   else "the nameplate's: not measured (needs a rotating test)"),
             "L_r": "L_s × the nameplate's L_r/L_s (not seen at standstill)",
             "M": "√(L_μ·L_r), L_μ = M²/L_r measured", "R_r": "α·L_r, α = R_r/L_r measured",
             "L_s": "σ + L_μ", "R_s": "at the start of the test"}
    where = "at standstill and rotating" if rotating else "at standstill"
    lines = [f"# Identified {where} by: {command}",
             f"# Run: {run_dir}. Use it with --motor FILE. SI units.", ""]
    for name in ("J", "R_s", "R_r", "L_s", "L_r", "M"):
        lines.append(f"{name} = {motor[name]!r}  # {_MOTOR_UNITS[name]}, {notes[name]}")
    lines += ["", f"[{COMMISSIONING}]  # measured besides model (1): not read as its "
                  "parameters", f'test = "{"standstill, rotating" if rotating else "standstill"}"']
    for name, what in {**_EXTRA, **(_FRICTION if rotating else {})}.items():
        e = values[name]
        lines.append(f"{name} = {e['value']!r}  # {what}; ± {e['std']:.2g} ({e['verdict']})")
        lines.append(f"{name}_std = {e['std']!r}  # its standard deviation (a value within "
                     "3 of them of no error is not corrected)")
    lines.append(f"residual_rms_V = {ident['residual_rms_V']!r}")
    return "\n".join(lines) + "\n"
