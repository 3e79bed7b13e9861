"""The whole bilateral loop through the real services over a bad link: the robot side (arm,
force, decision with `passivity` on) in one network namespace, the master station with the
simulated haptic operator in another, joined by the link of services/tools/tdpa/netem.py
(kernel netem where it exists, the userspace delay line otherwise): 200 ms round trip over
TCP, 10 % jitter and 1 % loss (`services.tools.tdpa.link_bench`,
which `telerobot bench passivity --link` runs at every delay). The operator presses the
tool onto the table, holds, releases.

What TDPA guarantees is checked (docs/passivity.md, "The whole loop over the link"): the
master port gives the hand no more energy than the slave sent, and the slave port puts no
more into the workcell than the master sent plus what the workcell gave back (its
reflection of an impact). And what the issue asks of it at this delay: the contact settles
(force RMS over the hold's last 3 s below 10 % of the steady force) with the operator
feeling it — the bench's protocol (500 Hz master, 8 s hold): calm in every bench run at
0–200 ms on 2026-11-26, and 3 of 3 with a busy core beside it; at 100 Hz with a 4 s hold
the operator has not settled yet and the force still climbs (0 of 4). Skipped with the
reason where the namespaces cannot be made.
"""

from __future__ import annotations

import pytest

from services.control.master.passivity import RESERVE_J
from services.control.passivity.controller import TOLERANCE_J
from services.tools.tdpa import link_bench as pl
from tests.tools.tdpa.link_runs import link_lost_the_operator, over_link

# Alone: the link is a userspace delay line and the master a 500 Hz loop in their own
# processes; beside a second test worker a command stalled past the 1.4 s watchdog once
# (fresh-clone CI, 2026-11-26) and the arm was held.
pytestmark = [pytest.mark.system, pytest.mark.alone, pytest.mark.timeout(180)]


ON_MUJOCO = (
    "issue 40, diagnosed 2026-12-02 and 2026-12-04 (docs/passivity.md, 'On the MuJoCo cell'):"
    " the protocol's old-probe geometry, the local loop (the master's contact damper) and the"
    " slave port's plunges after a loss (the drift back towards a surface just left at 1 mm/s)"
    " are fixed: the energy bounds now hold at 200 ms (0.0-0.2 mJ generated, was 12-21 mJ),"
    " and at 0 ms with TDPA on the press holds; but at 200 ms the press stays light (steady"
    " 0.45 N, felt 0.3-0.5 N): the fingertips' friction work (sideways stick-slip under the"
    " press) drains the slave port's budget - with the cell's friction at 0.2 both runs were"
    " stable at 4.7-5.2 N - open; not run in `make test` (each run takes a minute alone):"
    " `pytest --runxfail` runs them"
)


@pytest.mark.xfail(reason=ON_MUJOCO, strict=False, run=False)
def test_whole_loop_over_a_bad_link_stays_passive_and_settles() -> None:
    """200 ms with Zenoh peers over TCP. (700 ms over UDP keeps these too, but lost the
    master's liveliness once in 13 runs, which holds the arm: docs/passivity.md.)

    Over TCP too the link itself now and then stalls past the 2 s lease on a lost
    retransmission, and the operator's liveliness lapses (the decision then holds, as it
    must): 1 run in 8–12 on 2026-11-26, with this stop's code and with the code before it.
    Such a run measures the link's TCP, not the loop: it is run once more, and two in a row
    fail."""
    m = over_link(200.0, passivity=True)
    if link_lost_the_operator(m):
        first = m["events"]
        m = over_link(200.0, passivity=True)
        assert not link_lost_the_operator(m), ("the operator's session lapsed twice", first)
    # The run measured something: the operator brought the tool onto the table.
    assert m["peak_n"] >= pl.CONTACT_N and m["penetration_mm"] > 0.0, m
    assert len(m["force"]) > 1000
    # Master port: the hand got no more than the slave sent (plus the reserve and one late
    # tick's misprediction), by the master's own count and by the slave's.
    allowance = RESERVE_J + 0.01 + TOLERANCE_J
    assert m["op_master_out_j"] <= m["op_slave_in_seen_j"] + allowance, m
    assert m["master_out_j"] <= m["slave_in_j"] + allowance, m
    # Slave port: the workcell got no more than the master sent plus what it gave back.
    assert m["slave_out_j"] <= m["master_in_j"] + m["slave_recovered_j"] + 0.01, m
    assert pl.bench_measures(m)["energy_generated_j"] <= 0.01 + allowance
    # Nothing held the arm on the way: the link's stalls stay within the watchdogs.
    held = [e for e in m["events"] if "watchdog" in e]
    assert not held, held
    # The contact settled, and the operator feels most of its 8 N: every wrist force arrives
    # 100 ms after its robot-host stamp here, and the master displays it all the same
    # (before 2026-11-26 it showed 0 from ~150 ms; 6.7–7.2 N felt in the bench's runs).
    measures = pl.bench_measures(m)
    assert measures["stable"] is True, measures
    assert m["felt_n"] > 4.0, m["felt_n"]
    # Each port measured the round trip from the other's echoes, across the two namespaces:
    # at least the link's own 200 ms (less its jitter), more where TCP queued behind a loss.
    assert 180.0 <= m["slave_rtt_ms"] <= 5000.0, m["slave_rtt_ms"]
    assert 180.0 <= m["master_rtt_ms"] <= 5000.0, m["master_rtt_ms"]


@pytest.mark.xfail(reason=ON_MUJOCO, strict=False, run=False)
def test_a_turn_over_a_bad_link_is_passive_and_felt() -> None:
    """The same at 200 ms with a turn (`--link --twist`): the contact resists a turn about
    its normal, the operator turns its handle once the press has seated the tool until it
    feels 0.5 N·m, the master shows moments through its rotational port. Each rotational
    port gives out no more than the other sent (plus the reserve, a late tick, and at the
    slave what the workcell gave back); the moment contact is stable; and the hand feels
    it. Shown about the world's axes (before 2026-11-27) the moment pushed the hand along
    its turn, the master's port withheld it, and the hand felt 0.01–0.06 N·m."""
    m = over_link(200.0, passivity=True, twist=True)
    if link_lost_the_operator(m):
        first = m["events"]
        m = over_link(200.0, passivity=True, twist=True)
        assert not link_lost_the_operator(m), ("the operator's session lapsed twice", first)
    assert m["moment_peak_nm"] > 0.1 and len(m["moment"]) > 1000, m["moment_peak_nm"]
    allowance = RESERVE_J + 0.01 + TOLERANCE_J
    assert m["op_master_rot_out_j"] <= m["op_slave_rot_in_seen_j"] + allowance, m
    recovered = m["slave_rot_recovered_j"]
    assert m["slave_rot_out_j"] <= m["master_rot_in_j"] + recovered + 0.01, m
    moment = pl.moment_measures(m)
    assert moment["stable"] is True, moment
    assert moment["energy_generated_j"] <= 0.01 + allowance, moment
    assert m["moment_felt_nm"] > 0.3, m["moment_felt_nm"]
    assert pl.bench_measures(m)["stable"] is True  # the press holds beside the turn
