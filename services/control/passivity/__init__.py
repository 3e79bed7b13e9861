"""Time-domain passivity (TDPA) for the position–force bilateral loop: pure, no bus.

`observer` keeps the energy that crosses one port, `controller` the master-side (variable
damping on the displayed force) and slave-side (position correction of the commanded
motion) passivity controllers, `slave` the decision service's port, `rotation` the
rotational ports, `roundtrip` the round trip measured from the exchanged energies, `wire`
their figures on the bus, `dynamics` the models of the simulated haptic operator and
workcell contact (the master's `haptic_sim` device runs them). The whole loop in simulation
and its benches are services.tools.tdpa. docs/passivity.md.
"""
