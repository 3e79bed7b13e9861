"""The link bench's measures of the turn's moment (`--link --twist`), from a hand-made
trace: each signal taken with the sign it holds (the tool's about the world's z, the one
shown about the hand's), the rotational ports' balance, the verdicts."""

from __future__ import annotations

import math

import pytest

from services.bus.messages import PassivityState
from services.tools.tdpa import link_bench as pl

T0 = 1_000_000_000


def figures(side: str, e_in: float, e_out: float, rot_in: float, rot_out: float) -> PassivityState:
    return PassivityState(
        seq=1,
        t_ns=T0,
        master="op",
        engage=1,
        side=side,  # type: ignore[arg-type]
        enabled=True,
        e_in=e_in,
        e_out=e_out,
        dissipated_j=0.0,
        gain=0.0,
        active_steps=0,
        rot_e_in=rot_in,
        rot_e_out=rot_out,
    )


def test_the_moment_is_measured_with_its_own_sign_and_the_rotational_balance() -> None:
    """Over the window the tool's moment about the world's z holds at −0.8 N·m with a
    ±0.02 ripple, the one shown about the hand's z at +0.5: steady 0.8, felt 0.5, both
    positive against the turn; stable (swing well under 10 %). The rotational ports gave
    out 3 mJ for 2 + 0.5 mJ in and 0.4 repaid: 0.1 mJ generated."""
    trace = pl.Trace()
    for k in range(400):  # 4 s at 100 Hz
        t = T0 + k * 10_000_000
        trace.moments.append((t, -0.8 + (0.02 if k % 2 else -0.02)))
        trace.felt_moments.append((t, 0.5))
        trace.forces.append((t, 8.0))
        trace.force_norms.append(8.0)
        trace.states.append((t, 0.7))
        trace.felt.append((t, 7.5))
    trace.master.append(figures("master", 0.01, 0.002, 0.002, 0.001))
    trace.slave.append(figures("slave", 0.0005, 0.005, 0.0005, 0.002))
    m = pl.metrics(trace, T0, 1.0, 4.0)
    assert m["moment_steady_nm"] == pytest.approx(0.8, rel=1e-3)
    assert m["moment_felt_nm"] == pytest.approx(0.5)
    assert m["moment_peak_nm"] == pytest.approx(0.82)
    assert m["moment_rms_nm"] == pytest.approx(0.02, rel=1e-3)
    m |= {"passivity": True, "slave_rot_recovered_j": 0.0004}
    measures = pl.moment_measures(m)
    assert measures["stable"] is True and measures["settled"] is True
    assert measures["energy_generated_j"] == pytest.approx(0.0001)
    assert math.isnan(measures["penetration_mm"])
    # Without TDPA no energy is observed; a moment under the 0.1 N·m band is no contact.
    quiet = dict(m, passivity=False, moment_steady_nm=0.05)
    off = pl.moment_measures(quiet)
    assert math.isnan(off["energy_generated_j"]) and off["stable"] is False
