"""Time-domain passivity (TDPA) for the position–force bilateral loop: pure, no bus.

`observer` keeps the energy that crosses one port, `controller` the master-side (variable
damping on the displayed force) and slave-side (position correction of the commanded
motion) passivity controllers, `dynamics` the models of the simulated haptic operator and
workcell contact, `loop` a whole bilateral loop over a bad link. docs/passivity.md.
"""
