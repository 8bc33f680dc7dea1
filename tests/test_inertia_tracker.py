"""The inertia tracked on line (gateway/control/inertia_tracker.py, docs/robustness.md §9):
the filter on synthetic readings, and the paper's profile with J × 2 and × 0.5 tracked,
against the motor file's J."""

from __future__ import annotations

import cmath
import random

import numpy as np
import pytest
from sim_support import sim_config

from dbc.motor import MotorParams
from gateway.control.inertia_tracker import InertiaTracker
from gateway.guard import DivergenceWatch, profile_envelope
from gateway.reference import paper_profile
from gateway.simulate import run
from plant.scenario import parse_scenario, resolve_scenario

MOTOR = MotorParams.paper()


def _feed(tracker: InertiaTracker, rho_true: float, noise: float, n: int,
          seed: int = 1) -> list[float]:
    """The readings (I1) of a rotor accelerated by a smooth model torque: ω' = ρ·a."""
    rnd = random.Random(seed)
    w, applied = 0.0, []
    for k in range(n):
        a = 800.0 * np.sin(np.pi * k / n) ** 2  # rad/s², the model's acceleration
        A = a * 1e-3
        w_mid = w + 0.5 * rho_true * A  # the rotor's mean speed over the interval
        e = rnd.gauss(0.0, noise)  # the reading's error
        applied.append(tracker.update(w_mid + 0.3 + e, 0.3 + e, A, 1.16 ** 2))
        w += rho_true * A
    return applied


@pytest.mark.parametrize("rho_true", [0.5, 2.0])
def test_a_wrong_inertia_is_rejected_and_tracked(rho_true):
    tracker = InertiaTracker()
    applied = _feed(tracker, rho_true, 0.03, 200)
    assert tracker.switched
    first = next(k for k, r in enumerate(applied) if r != 1.0)
    assert first < 60, first  # within the first 60 ms of the acceleration
    assert tracker.rho == pytest.approx(rho_true, rel=0.01)
    assert applied[-1] == pytest.approx(rho_true, rel=0.01)
    assert tracker.rho_std < 0.01


@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5])
def test_the_files_inertia_is_kept_when_it_is_right(seed):
    """Noisy readings of a rotor that is the model (ρ = 1): never switched, 1 applied."""
    tracker = InertiaTracker()
    applied = _feed(tracker, 1.0, 0.4, 2000, seed)
    assert not tracker.switched and set(applied) == {1.0}
    assert tracker.rho == pytest.approx(1.0, abs=0.05)


def test_no_reading_no_information():
    """Intervals without a reading (weight 0: the frame held at standstill) predict only:
    ρ̂ stays the prior."""
    tracker = InertiaTracker()
    for _ in range(100):
        assert tracker.update(0.0, 0.0, 0.5, 0.0) == 1.0
    assert tracker.rho == 1.0 and not tracker.switched and not tracker.frozen
    assert tracker.speed == pytest.approx(50.0)


def test_a_long_coast_stops_the_readings():
    """Lost samples the controller coasted through: one reopens D's prior and the readings
    go on; three in a row (an unknown late latch may follow) stop them, the applied ρ kept."""
    tracker = InertiaTracker()
    _feed(tracker, 1.0, 0.03, 50)
    tracker.coast(0.0)
    assert not tracker.frozen
    w = tracker.speed  # a reading that agrees with the filter
    assert tracker.update(w + 0.3, 0.3, 0.0, 1.0) == 1.0 and tracker._coasts == 0
    for _ in range(3):
        tracker.coast(0.5)
    assert tracker.frozen
    rho = tracker.rho
    assert tracker.update(1000.0, -500.0, 0.5, 1.0) == 1.0  # a wild reading: not taken
    assert tracker.rho == rho and not tracker.switched


def _feed_flux_error(tracker: InertiaTracker, D: complex, with_g: bool, seed: int) -> None:
    """(I3): readings of a rotor that is the model, accelerated into field weakening
    (|ψ| = 0.5 Wb), rippled by a flux error D constant in (a, b): Im(g·D), g turning with
    the frame."""
    rnd = random.Random(seed)
    w = eps = 0.0
    n, T, psi = 600, 1e-3, 0.5
    for k in range(n):
        A = 700.0 * np.sin(np.pi * k / n) ** 2 * T
        w_mid = w + 0.5 * A
        g = cmath.exp(-1j * eps) * complex(8.8, -w_mid) / psi
        y = w_mid + (g * D).imag + rnd.gauss(0.0, 0.03)
        tracker.update(w_mid + 0.3, w_mid + 0.3 - y, A, psi * psi, g if with_g else 0j)
        w += A
        eps += w * T


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_flux_error_constant_in_ab_is_estimated_not_read_as_inertia(seed):
    """A 3.6 mWb flux error (what a residual 0.4 mA offset integrates to in two seconds)
    ripples the reading by ±1.4 rad/s at the stator frequency: without its term the test
    rejects the right J; with it, D is found and J kept."""
    D = 0.003 + 0.002j
    tracker = InertiaTracker()
    _feed_flux_error(tracker, D, True, seed)
    assert not tracker.switched
    assert abs(tracker.flux_error - D) < 2e-4
    blind = InertiaTracker()
    _feed_flux_error(blind, D, False, seed)
    assert blind.switched


def test_the_r_s_adaptation_keeps_the_files_j():
    """Where the tracker is not built, summary.json says why; the full-order law tracks J
    too (its reading from the joint (i, ψ) model, docs/robustness.md §9)."""
    from gateway.control.controller import ControllerConfig
    from gateway.control.sampled import make_controller

    cfg = ControllerConfig(discretisation="exact", identify=True, inertia="tracked",
                           estimator="rs-adaptive")
    ctl = make_controller(MOTOR, cfg, paper_profile().at)
    assert getattr(ctl, "inertia", None) is None
    found = ctl.summary()["inertia"]
    assert not found["applied"] and "R_s adaptation" in found["reason"]
    cfg = ControllerConfig(discretisation="exact", identify=True, inertia="tracked",
                           law="full-order")
    assert make_controller(MOTOR, cfg, paper_profile().at).inertia is not None


FULL_ORDER = {"law": "full-order", "drive": "voltage"}


def _paper(plant: str, inertia: str, **kw):
    profile = paper_profile()
    watch = DivergenceWatch(profile_envelope(profile, MOTOR, 14.0))
    spec = sim_config(plant=resolve_scenario(plant), discretisation="exact", identify=True,
                      inertia=inertia, **kw)
    rec = run(profile, MOTOR, spec, watch=watch).arrays()
    e = rec["w_m"] - rec["w_ref"]
    return float(np.sqrt(np.mean(e ** 2))), watch.reason, len(e), rec


@pytest.mark.slow
@pytest.mark.parametrize("plant", ["inertia-double", "inertia-half"])
def test_the_tracked_inertia_runs_the_paper_profile_with_the_wrong_j(plant):
    """The robustness target: no guard stop, ≤ 0.05 rad/s RMS (measured 0.0147 and
    0.0206); with the file's J (``--inertia file``) the same run stops (J × 2) or is off by
    rad/s."""
    rms, reason, n, _ = _paper(plant, "tracked")
    assert reason is None and n == 2500
    assert rms <= 0.035, rms
    rms_file, reason_file, _, _ = _paper(plant, "file")
    assert reason_file is not None or rms_file > 1.0, (rms_file, reason_file)


@pytest.mark.slow
@pytest.mark.parametrize("plant", ["inertia-double", "inertia-half"])
def test_the_full_order_law_tracks_the_inertia_too(plant):
    """The full-order law with its voltage drive: with the file's J the paper profile stops
    (J × 2, J × 0.5: its speed loop's gain kω·T·J_file/J leaves kω·T < 1, §11); tracked,
    J is found within 1 % and the run meets the target (measured 0.0110, 0.0146)."""
    rms, reason, n, _ = _paper(plant, "tracked", **FULL_ORDER)
    assert reason is None and n == 2500
    assert rms <= 0.035, rms
    rms_file, reason_file, _, _ = _paper(plant, "file", **FULL_ORDER)
    assert reason_file is not None or rms_file > 1.0, (rms_file, reason_file)


@pytest.mark.slow
def test_the_full_order_law_reads_no_inertia_while_no_torque_is_asked():
    """This law's filter reads from the standstill on; there the model's torque is the
    sensors' error alone. With the true flux and phase b's gain 2 % high that spurious
    torque had J rejected at 0.255 s of the magnetisation (the run then 3.36 rad/s RMS, max
    22). ρ held while the references ask no torque: the file's J kept, 0.088."""
    rms, reason, n, rec = _paper("gain-b+2", "tracked", flux="true", **FULL_ORDER)
    assert reason is None and n == 2500
    assert rms <= 0.2, rms
    _, _, _, file = _paper("gain-b+2", "file", flux="true", **FULL_ORDER)
    assert np.array_equal(rec["w_hat"], file["w_hat"])  # J never switched


@pytest.mark.slow
@pytest.mark.parametrize(("plant", "kw"), [
    ("nominal", {}), ("offset10mA-rs+10", {}), ("offset10mA-rs-20", {}),
    ("offset10mA-rs+10", FULL_ORDER), ("rs-20", FULL_ORDER)])
def test_a_motor_with_the_files_j_is_the_files_bit_for_bit(plant, kw):
    """Never switched, so the same numbers; with the offset and an R_s error the readings
    carry the flux error (I3), which (I2) alone read as inertia (0.0155 → 0.048 rad/s RMS)."""
    _, _, _, tracked = _paper(plant, "tracked", **kw)
    _, _, _, file = _paper(plant, "file", **kw)
    for name in ("w_m", "w_hat", "i_sq_ref", "u_sa"):
        assert np.array_equal(tracked[name], file[name]), name


def test_a_settled_inertia_stops_the_filter_unless_the_load_is_observed():
    """J is constant: once σ_ρ < 0.002 the filter stops and a later reading, however wild
    (an untold load step read as inertia), changes nothing; with the load observed it goes
    on (the load is not constant)."""
    tracker = InertiaTracker()
    _feed(tracker, 1.0, 0.03, 400)
    assert tracker.settled and tracker.frozen and tracker.rho_std < 0.002
    assert tracker.update(500.0, -500.0, 0.5, 1.0) == 1.0 and not tracker.switched
    observed = InertiaTracker(T=1e-3, load=True)
    _feed(observed, 1.0, 0.03, 400)
    assert not observed.settled and not observed.frozen


def test_a_told_load_that_is_wrong_is_rejected_once_j_is_settled():
    """(I5): after ρ settled with the load told, the filter watches the readings on (ω, D)
    alone; a rotor at the told load is never rejected, and one that a 5.8 N·m load the laws
    are not told decelerates (773 rad/s² on the paper's J) is rejected at the third reading,
    after which the filter observes that load as with ``--load observed``."""
    tracker = InertiaTracker()
    _feed(tracker, 1.0, 0.03, 400)
    assert tracker.frozen and tracker.settled
    w = tracker.speed  # the rotor's speed at the end of the acceleration
    rnd = random.Random(3)
    for _ in range(2000):  # at the told load: 2000 noisy readings, none rejects it
        e = rnd.gauss(0.0, 0.03)
        assert not tracker.watch(w + 0.3 + e, 0.3 + e, 0.0, 1.16 ** 2)
    assert tracker.frozen and tracker.applied == 1.0
    a, T = 773.0, 1e-3
    rejected = []
    for _k in range(300):
        e = rnd.gauss(0.0, 0.03)
        y = w - 0.5 * a * T  # the rotor's mean speed over the interval
        if tracker.frozen:
            rejected.append(tracker.watch(y + 0.3 + e, 0.3 + e, 0.0, 1.16 ** 2))
        else:
            tracker.update(y + 0.3 + e, 0.3 + e, 0.0, 1.16 ** 2)
        w -= a * T
    assert rejected == [False, False, True]  # three readings beyond 4σ, one sign
    assert tracker.load == pytest.approx(a, rel=0.02)
    assert tracker.speed == pytest.approx(w, abs=0.1)
    assert tracker.applied == 1.0  # J as it settled


@pytest.mark.slow
def test_the_untold_load_plant_with_its_load_told_completes_by_default():
    """The shipped untold-load scenario tells the profile's load, and the shaft carries a
    further 5.8 N·m from 1.2 s: the default run rejects the told load within 10 ms and
    completes (the motor file's J: stopped by the guard, there being no tracker)."""
    profile = paper_profile()
    watch = DivergenceWatch(profile_envelope(profile, MOTOR, 14.0))
    spec = sim_config(plant=resolve_scenario("untold-load"), discretisation="exact",
                      identify=True)
    rec = run(profile, MOTOR, spec, watch=watch)
    sig = rec.arrays()
    e = sig["w_m"] - sig["w_ref"]
    assert watch.reason is None and len(e) == 2500
    assert float(np.sqrt(np.mean(e ** 2))) <= 0.25  # measured 0.166
    found = rec.identification["inertia"]
    assert 1.2 < found["load_rejected_at"] < 1.21
    assert found["T_L_observed"] == pytest.approx(5.8, abs=0.1)
    assert not found["applied"]  # J kept: the file's
    _, reason_file, _, _ = _paper("untold-load", "file")
    assert reason_file is not None


@pytest.mark.slow
def test_the_full_order_law_watches_its_told_load_too():
    """The untold-load scenario with the full-order law on its voltage drive: the further
    5.8 N·m from 1.2 s rejects the told load within 10 ms, the load it leaves out is found,
    and the run completes (it was stopped by the guard at 1.28 s). In field weakening the
    drive cannot carry that load at the profile's speed: at its voltage and current limits
    from 2 s the speed stays 17 rad/s below the reference (measured 9.55 rad/s RMS)."""
    profile = paper_profile()
    spec = sim_config(plant=resolve_scenario("untold-load"), discretisation="exact",
                      identify=True, law="full-order", drive="voltage")
    watch = DivergenceWatch(profile_envelope(profile, MOTOR, spec.gains.i_max))
    rec = run(profile, MOTOR, spec, watch=watch)
    assert watch.reason is None and len(rec.arrays()["t"]) == 2500
    found = rec.identification["inertia"]
    assert 1.2 < found["load_rejected_at"] < 1.21, found
    assert found["T_L_observed"] == pytest.approx(5.8, abs=0.2), found
    sig = rec.arrays()
    before = sig["t"] < 1.2
    e = sig["w_m"] - sig["w_ref"]
    # before it, the told load's run (measured 0.105: this scenario's dynamometer takes
    # the profile's load within the period, docs/robustness.md §10)
    assert float(np.sqrt(np.mean(e[before] ** 2))) < 0.15


def _watching(seed: int = 3) -> tuple[InertiaTracker, float, random.Random]:
    """A tracker whose ρ settled (load told), watching 500 readings of a rotor at the told
    load; its speed and the noise's generator."""
    tracker = InertiaTracker()
    _feed(tracker, 1.0, 0.03, 400)
    w = tracker.speed
    rnd = random.Random(seed)
    for _ in range(500):
        e = rnd.gauss(0.0, 0.03)
        assert not tracker.watch(w + 0.3 + e, 0.3 + e, 0.0, 1.16 ** 2)
    return tracker, w, rnd


def test_the_watch_takes_a_jump_of_the_reading_not_as_a_load():
    """(I5) rejects a told load on outliers that grow: a step of the reading's bias (what
    an imperfect drive model leaves after a told load's own step) is taken after max_gate
    outliers, with ω's variance reopened, and does not reject the told load."""
    tracker, w, rnd = _watching()
    for _ in range(500):  # a jump of 0.5 rad/s (about 15σ), then constant
        e = rnd.gauss(0.0, 0.03)
        assert not tracker.watch(w + 0.5 + 0.3 + e, 0.3 + e, 0.0, 1.16 ** 2)
    assert tracker.frozen and tracker.speed == pytest.approx(w + 0.5, abs=0.05)


def test_the_told_load_is_watched_except_on_a_pi_current_loop():
    """On the PI current loop the load observed (I4), which the watch hands over to, is not
    robust, and a current-sensor gain error makes the speed ripple by up to 3 rad/s, which
    the watch took for a load: no watch there. The ideal source and the full-order law's
    voltage drive are watched."""
    from gateway.control.controller import ControllerConfig
    from gateway.control.sampled import make_controller

    for kw, watched in (({}, True), ({"current_lag": 2e-4}, False),
                        ({"law": "full-order"}, True)):
        cfg = ControllerConfig(discretisation="exact", identify=True, inertia="tracked", **kw)
        assert make_controller(MOTOR, cfg, paper_profile().at)._load_watch is watched, kw


def test_the_watch_counts_nothing_while_told_so_and_stops_after_a_long_coast():
    """``count`` False (the told load moving): a real deceleration is taken, not counted;
    three lost intervals in a row stop the watch for good (the estimator's integral is
    not known after them), one reopens D's prior."""
    a, T = 773.0, 1e-3
    tracker, w, rnd = _watching()
    for _ in range(30):
        e = rnd.gauss(0.0, 0.03)
        assert not tracker.watch(w - 0.5 * a * T + 0.3 + e, 0.3 + e, 0.0, 1.16 ** 2,
                                 count=False)
        w -= a * T
    tracker, w, rnd = _watching()
    tracker.watch(0.0, 0.0, 0.0, 0.0, lost=True)
    assert tracker.flux_error is not None and tracker._p33 >= tracker.tuning.p_d_lost
    for _ in range(2):
        tracker.watch(0.0, 0.0, 0.0, 0.0, lost=True)
    for _ in range(50):
        e = rnd.gauss(0.0, 0.03)
        assert not tracker.watch(w - 0.5 * a * T + 0.3 + e, 0.3 + e, 0.0, 1.16 ** 2)
        w -= a * T


def _drop_at(cycle: int):
    """A plant scenario: the nominal motor, the drive's TPDO1 lost once at ``cycle``."""
    return parse_scenario(f'[[bus.fault]]\nkind = "drop"\nmessage = "TPDO1"\n'
                          f'cycle = {cycle}\nduration = 0.001\n', f"drop{cycle}")


@pytest.mark.slow
@pytest.mark.parametrize("cycle", [100, 101, 201])
def test_a_sample_lost_at_the_told_loads_step_stops_the_watch_not_the_told_load(cycle):
    """At 5 ms a sample lost as the told load steps (0.5 s, and its step down at 1 s):
    the drive's response to the step is never read and the loop rings after the coast
    (±1.9 rad/s in (I1) for over 0.3 s), which the watch (I5) took for a load the laws are
    not told: it rejected the told load (at 0.545 s) and, with ω̂'s pull to the filter at
    k_s·T = 2.5, the run ran away (a guard stop at 0.595 s). Now the watch stops there, the
    told load stands, and the run costs what the coast itself costs (the motor file's J, no
    tracker: the same numbers)."""
    profile = paper_profile()
    plant = _drop_at(cycle)
    results = []
    for inertia in ("tracked", "file"):
        watch = DivergenceWatch(profile_envelope(profile, MOTOR, 14.0))
        spec = sim_config(period=5e-3, plant=plant, discretisation="exact", identify=True,
                          inertia=inertia)
        rec = run(profile, MOTOR, spec, watch=watch)
        sig = rec.arrays()
        e = sig["w_m"] - sig["w_ref"]
        assert watch.reason is None and len(e) == 499, (inertia, watch.reason)
        results.append((float(np.sqrt(np.mean(e ** 2))), rec.identification.get("inertia")))
    (rms, found), (rms_file, _) = results
    assert "load_rejected_at" not in found and "T_L_observed" not in found, found
    assert abs(found["load_watch_stopped_at"] - 0.005 * cycle) <= 0.0101, found
    assert rms <= 1.05 * rms_file and rms < 0.5, (rms, rms_file)  # measured 0.26 both


@pytest.mark.slow
def test_a_sample_lost_away_from_the_told_loads_steps_leaves_the_watch_on():
    """A lost sample at steady speed and load (5 ms, 0.6 s) reopens D's prior only: the
    watch goes on, and nothing is rejected."""
    profile = paper_profile()
    spec = sim_config(period=5e-3, plant=_drop_at(120), discretisation="exact",
                      identify=True)
    rec = run(profile, MOTOR, spec)
    found = rec.identification["inertia"]
    assert "load_watch_stopped_at" not in found and "load_rejected_at" not in found, found
