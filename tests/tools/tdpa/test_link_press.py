"""The press on the MuJoCo table over the link at 0 ms, TDPA off and on, through the real
services in two network namespaces (`services.tools.tdpa.link_bench`, as
`test_link_loop.py`): the local loop's own stability, which the 200 ms tests there build
on (docs/passivity.md, "On the MuJoCo cell"; docs/master.md, "Contact damping").

Both alone (one test at a time), each run about 18 s. With TDPA off: that loop is stable
only while its own delay is short (the master's damper covers about k·τ,
`link_bench.CONTACT_DAMPING_NS_M`), and in CI's system pass (2026-12-04, a second worker
beside it on CI's two cores) the tool bounced off the table once (steady 1.0 N, felt
−0.4 N, peaks 12.9 N). With TDPA on the ports keep the loop passive whatever its delay,
but the press is still the quiet case's claim: in `make test`'s system pass (2026-12-04
20:25 UTC, the other worker on the browser and profile tests) the PUMA's tool struck the
table once (peak 15.6 N, steady 2.5 N, the press not held; nothing generated beyond
2 mJ), where beside one busy core it held in 10 of 10 runs (2026-12-04 04:47 UTC) and
again today, with the FR3 and the UR5e.

With TDPA, for every shipped arm on its MuJoCo cell: each model's tool, servo and joints
make their own contact loop (at 0 ms, 2026-12-04, quiet, three runs each: steady
4.8–6.0 N, felt 4.5–5.7 N for the FR3; steady 3.6–5.7 N, felt 3.7–5.4 N for the UR5e).
Without TDPA the test presses with the PUMA only (the FR3's and the UR5e's held at
6.2–6.3 N in every bench run, docs/passivity.md "The FR3 and the UR5e over the link").
"""

from __future__ import annotations

import pytest

from services.control.arm.model import SHIPPED
from services.control.master.passivity import RESERVE_J
from services.control.passivity.controller import TOLERANCE_J
from services.tools.tdpa import link_bench as pl
from tests.tools.tdpa.link_runs import assert_the_press_held, link_lost_the_operator, over_link

pytestmark = [pytest.mark.system, pytest.mark.timeout(180)]


@pytest.mark.alone
def test_the_local_loop_holds_a_press_on_the_mujoco_table() -> None:
    """0 ms, TDPA off, through the same services and namespaces: the operator presses the
    fingertips onto the MuJoCo table and the press holds through the hold. Before the
    master's contact damper (`[master] contact_damping_ns_m`, 250 N·s/m in the link bench)
    the tool bounced off the table every 0.5–0.8 s here (steady 0.3–1.5 N, peaks 14–23 N):
    each newton shown lifted the softly held hand 17 times as far as it pressed the tool
    (docs/master.md, "Contact damping"). Without the passivity layer this is the quiet case's
    claim: beside a second test worker on CI's host the bounce came back (module docstring)."""
    m = over_link(0.0, passivity=False)
    if link_lost_the_operator(m):
        m = over_link(0.0, passivity=False)
    assert m["peak_n"] >= pl.CONTACT_N and m["penetration_mm"] > 0.0, m
    assert_the_press_held(m)
    assert m["peak_n"] < pl.SUPERVISOR_LIMIT_N, m["peak_n"]


@pytest.mark.alone
@pytest.mark.parametrize("model", SHIPPED)
def test_with_tdpa_the_local_loop_holds_the_press_and_stays_passive(model: str) -> None:
    """0 ms, TDPA on: both ports' bounds hold and so does the press. Before the slave
    port's drift went back towards a surface just left at DRIFT_CONTACT_M_S, a strike lost
    the press here and the tool hovered above the table for the rest of the hold (17 N,
    8 mJ forgiven; docs/passivity.md, "On the MuJoCo cell")."""
    m = over_link(0.0, passivity=True, model=model)
    if link_lost_the_operator(m):
        m = over_link(0.0, passivity=True, model=model)
    assert m["peak_n"] >= pl.CONTACT_N and m["penetration_mm"] > 0.0, m
    allowance = RESERVE_J + 0.01 + TOLERANCE_J
    assert m["master_out_j"] <= m["slave_in_j"] + allowance, m
    assert m["slave_out_j"] <= m["master_in_j"] + m["slave_recovered_j"] + 0.01, m
    assert pl.bench_measures(m)["energy_generated_j"] <= 0.01 + allowance, m
    assert_the_press_held(m, least_n=3.0)
