"""A drive test of your own: `pytest examples/test_my_drive.py` (the can-drive-hil plugin
gives the drive_run fixture; README, "Drive tests of your own with pytest")."""

from gateway import drivecheck as check


def test_the_ifoc_baseline_takes_the_speed_step(drive_run):
    run = drive_run("quick", where="sim", controller="ifoc")  # over CANopen, in this process
    check.assert_no_fault(run)
    check.assert_settles(run, within=0.2, after=0.15)               # 0 → 100 rad/s, into ±2 %
    check.assert_overshoot_below(run, 5.0, after=0.15, until=0.34)  # % of the step
    check.assert_steady_state_error(run, 0.5, window=(0.30, 0.34))  # rad/s, before the load
    check.assert_current_peak_below(run, 15.0)                      # A
