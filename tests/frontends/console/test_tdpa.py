"""The console's passivity panel (docs/console.md, "Passivity"): the view model of the two
sides' PassivityState (energies, reservoir, the controller's action, active/inactive), its
HTML, the mirror that takes the figures only while a page is shown, and the page itself as
a browser receives it."""

from __future__ import annotations

import html
import math
import time
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.bus import keys
from services.bus.messages import PassivityState
from services.frontends.console.app import Console
from services.frontends.console.config import ConsoleConfig
from services.frontends.console.mirror import BusMirror
from services.frontends.console.tdpa import (
    ACTING_HOLD_S,
    FRESH_S,
    PortSeen,
    TdpaView,
    plot_row,
    tdpa_view,
)
from services.frontends.console.view import passivity_html

from .support import FakeBrowser, gui_uuid, wait_until


def fig(
    side: str,
    seq: int = 1,
    e_in: float = 0.0,
    e_out: float = 0.0,
    engage: int = 1,
    master: str = "m1",
    gain: float = 0.0,
    steps: int = 0,
    enabled: bool = True,
    dissipated: float = 0.0,
) -> PassivityState:
    return PassivityState(
        seq=seq,
        t_ns=time.time_ns(),
        master=master,
        engage=engage,
        side=side,  # type: ignore[arg-type]
        enabled=enabled,
        e_in=e_in,
        e_out=e_out,
        dissipated_j=dissipated,
        gain=gain,
        active_steps=steps,
    )


# --- the view model ---------------------------------------------------------------------------
def test_reservoirs_pair_the_two_sides_of_one_engagement() -> None:
    seen = {
        "master": PortSeen.first(fig("master", e_in=0.30, e_out=0.05), 10.0),
        "slave": PortSeen.first(fig("slave", e_in=0.12, e_out=0.20), 10.0),
    }
    v = tdpa_view(seen, 10.1)
    m, s = v.port("master"), v.port("slave")
    assert m is not None and s is not None
    # master: slave in − master out; slave: master in − slave out
    assert m.remote_in_j == 0.12 and m.reservoir_j == pytest.approx(0.07)
    assert s.remote_in_j == 0.30 and s.reservoir_j == pytest.approx(0.10)
    assert [p.side for p in v.ports] == ["master", "slave"]
    assert v.state == "inactive"
    assert plot_row(v) == pytest.approx((0.07, 0.10, 0.0, 0.0))


def test_another_engagement_or_master_counts_for_nothing() -> None:
    for other in (fig("slave", e_in=0.5, engage=2), fig("slave", e_in=0.5, master="m2")):
        seen = {
            "master": PortSeen.first(fig("master", e_in=0.3, e_out=0.05), 0.0),
            "slave": PortSeen.first(other, 0.0),
        }
        m = tdpa_view(seen, 0.0).port("master")
        assert m is not None and m.remote_in_j is None and m.reservoir_j == pytest.approx(-0.05)


def test_stale_sides_are_not_shown_and_none_means_off() -> None:
    seen = {
        "master": PortSeen.first(fig("master", e_in=0.3), 0.0),
        "slave": PortSeen.first(fig("slave", e_in=0.1), 0.5),
    }
    assert [p.side for p in tdpa_view(seen, FRESH_S).ports] == ["master", "slave"]
    v = tdpa_view(seen, FRESH_S + 0.1)
    assert [p.side for p in v.ports] == ["slave"]
    slave = v.port("slave")
    assert slave is not None and slave.remote_in_j is None  # a stale side is no partner
    v = tdpa_view(seen, FRESH_S + 0.6)
    assert v.ports == () and v.state == "none" and plot_row(v) == (0.0, 0.0, 0.0, 0.0)
    assert tdpa_view({}, 0.0).state == "none"


def test_acting_is_seen_through_the_step_count_and_held_briefly() -> None:
    rec = PortSeen.first(fig("slave", seq=1, steps=0), 0.0)
    assert not tdpa_view({"slave": rec}, 0.0).ports[0].acting
    # The console missed the acting ticks (downsampled): the count grew, the gain is 0 now.
    rec = rec.after(fig("slave", seq=9, steps=3, dissipated=0.01), 1.0)
    v = tdpa_view({"slave": rec}, 1.0)
    assert v.ports[0].acting and v.state == "active"
    assert tdpa_view({"slave": rec}, 1.0 + ACTING_HOLD_S).state == "active"
    rec = rec.after(fig("slave", seq=10, steps=3, dissipated=0.01), 1.2)
    assert tdpa_view({"slave": rec}, 1.2 + ACTING_HOLD_S + 0.01).state == "inactive"
    # A non-zero gain is acting now.
    rec = rec.after(fig("slave", seq=11, steps=4, gain=1e-4), 3.0)
    assert tdpa_view({"slave": rec}, 3.0).ports[0].acting
    # A new engagement starts its count again: a few steps in it are new ones.
    rec2 = PortSeen.first(fig("master", seq=1, steps=50, engage=1), 0.0).after(
        fig("master", seq=2, steps=2, engage=2), 5.0
    )
    assert rec2.acted_s == 5.0
    same = PortSeen.first(fig("master", seq=1, steps=50), 0.0).after(
        fig("master", seq=2, steps=50), 5.0
    )
    assert same.acted_s == 0.0  # acting at the first message, not since


def test_controllers_off_is_observing_not_inactive() -> None:
    seen = {"master": PortSeen.first(fig("master", enabled=False, e_out=0.2), 0.0)}
    assert tdpa_view(seen, 0.0).state == "observing"


# --- the HTML ---------------------------------------------------------------------------------
def test_the_panel_says_off_inactive_or_active_and_shows_each_port() -> None:
    off = passivity_html(TdpaView(()))
    assert 'data-tdpa="none"' in off and "passivity off" in off and "tr-tdpa-port" not in off
    seen = {
        "master": PortSeen.first(fig("master", e_in=0.3, e_out=0.05, gain=2.5, steps=4), 0.0),
        "slave": PortSeen.first(fig("slave", e_in=0.12, e_out=0.2), 0.0),
    }
    out = passivity_html(tdpa_view(seen, 0.1))
    assert 'data-tdpa="active"' in out and "TDPA ACTIVE" in out
    assert 'data-side="master" data-acting="true"' in out
    assert 'data-side="slave" data-acting="false"' in out
    assert f'data-reservoir="{0.12 - 0.05!r}" data-gain="2.5"' in out
    assert "β (N·s/m)" in out and "α (m/N)" in out
    assert ">+0.3000<" in out and ">+0.0700<" in out and ">+0.1000<" in out
    quiet = passivity_html(tdpa_view(seen, ACTING_HOLD_S + 0.1))
    assert 'data-tdpa="inactive"' in quiet and "TDPA on — inactive" in quiet
    assert "tr-tdpa-felt" not in out  # no figures of the hand reported


def test_the_master_port_shows_what_the_hand_feels_of_what_it_was_asked() -> None:
    held = replace(fig("master", steps=3), asked_n=10.46, shown_n=7.74)
    v = tdpa_view({"master": PortSeen.first(held, 0.0)}, 0.1)
    m = v.port("master")
    assert m is not None and (m.asked_n, m.shown_n) == (10.46, 7.74)
    out = passivity_html(v)
    assert "hand feels (N)" in out and ">7.74 of 10.46<" in out


def test_the_slave_port_shows_what_was_repaid_and_forgiven_of_its_overdraws() -> None:
    slave = replace(fig("slave", steps=2), repaid_j=0.0021, forgiven_j=0.0004)
    v = tdpa_view({"slave": PortSeen.first(slave, 0.0)}, 0.1)
    s = v.port("slave")
    assert s is not None and (s.repaid_j, s.forgiven_j) == (0.0021, 0.0004)
    out = passivity_html(v)
    assert "overdraw repaid (J)" in out and ">+0.0021<" in out
    assert "forgiven (J)" in out and ">+0.0004<" in out
    plain = passivity_html(tdpa_view({"slave": PortSeen.first(fig("slave"), 0.0)}, 0.1))
    assert "tr-tdpa-forgiven" not in plain  # not reported: no row


@given(st.text(min_size=1, max_size=128), st.floats(0.0, 1e6), st.floats(0.0, 1e6))
def test_bus_text_is_escaped_and_the_reservoir_is_remote_in_minus_out(
    master: str, e_in: float, e_out: float
) -> None:
    seen = {
        "master": PortSeen.first(fig("master", master=master, e_out=e_out), 0.0),
        "slave": PortSeen.first(fig("slave", master=master, e_in=e_in), 0.0),
    }
    v = tdpa_view(seen, 0.0)
    m = v.port("master")
    assert m is not None and m.reservoir_j == e_in - e_out
    out = passivity_html(v)
    assert f"{html.escape(master, quote=True)} #1" in out
    if any(c in master for c in '<>&"'):
        assert f"{master} #1" not in out


# --- the mirror -------------------------------------------------------------------------------
@pytest.mark.system
def test_the_mirror_takes_the_figures_only_for_a_page_and_refuses_a_wrong_side(net: Any) -> None:
    tdpa = net.node("tdpa")
    node = net.node("console")
    mirror = BusMirror(node, events=5, force_capacity=100, tdpa_capacity=64)
    pm, ps = tdpa.publisher(keys.PASSIVITY_MASTER), tdpa.publisher(keys.PASSIVITY_SLAVE)
    assert mirror.passivity().state == "none"
    mirror.watch_page(True)
    seq = iter(range(1, 10_000))

    def both_seen() -> bool:
        k = next(seq)
        pm.put(fig("master", seq=k, e_in=0.3, e_out=0.05))
        ps.put(fig("slave", seq=k, e_in=0.12, e_out=0.2, gain=1e-4, steps=k))
        v = mirror.passivity()
        return len(v.ports) == 2

    assert wait_until(both_seen, poll_s=0.02)
    v = mirror.passivity()
    assert v.state == "active"
    m = v.port("master")
    assert m is not None and m.reservoir_j == pytest.approx(0.07)
    t, w = mirror.tdpa.window(5.0, 100)
    assert len(t) >= 1 and np.all(np.diff(t) >= 0)
    assert w[-1, 0] == pytest.approx(0.07) and w[-1, 1] == pytest.approx(0.10)

    # An older message (lower seq, earlier t_ns) does not replace the newest.
    pm.put(replace(fig("master", seq=1, e_in=9.0), t_ns=1))
    # The slave's figures on the master's key: refused, reported, not shown.
    pm.put(fig("slave", seq=next(seq), e_in=5.0))
    assert wait_until(lambda: node.rejected.get(keys.PASSIVITY_MASTER.key, 0) == 1)
    m = mirror.passivity().port("master")
    assert m is not None and m.e_in_j == 0.3

    mirror.watch_page(False)
    assert mirror.passivity().state == "none" and mirror.watching == (False, False)


# --- the page ---------------------------------------------------------------------------------
def _uplot(browser: FakeBrowser, title: str) -> str:
    found: list[str] = []

    def look() -> bool:
        with browser._lock:
            found.extend(u for u, p in browser._gui.items() if p.get("title") == title)
        return bool(found)

    assert wait_until(look), f"no plot {title!r} reached the page"
    return found[0]


@pytest.mark.system
@pytest.mark.timeout(120)
def test_the_page_shows_tdpa_when_the_figures_flow_and_off_when_they_stop(net: Any) -> None:
    tdpa = net.node("tdpa")
    console = Console(net.node("console"), ConsoleConfig(port=0, shadows=False, gui_rate_hz=20.0))
    pm, ps = tdpa.publisher(keys.PASSIVITY_MASTER), tdpa.publisher(keys.PASSIVITY_SLAVE)
    try:
        with FakeBrowser(console.port, decode=True) as browser:
            panel = gui_uuid(browser, 'id="tr-tdpa"')
            plot = _uplot(browser, "energy (J)")
            assert 'data-tdpa="none"' in browser.gui(panel)["content"]
            assert browser.gui(plot).get("visible") is False
            k = 0

            def shown(state: str) -> bool:
                nonlocal k
                k += 1
                acting = state == "active"
                pm.put(fig("master", seq=k, e_in=0.01 * k, e_out=0.001 * k))
                ps.put(
                    fig(
                        "slave",
                        seq=k,
                        e_in=0.004 * k,
                        e_out=0.002 * k,
                        gain=2e-4 if acting else 0.0,
                        steps=k if acting else 0,
                    )
                )
                return f'data-tdpa="{state}"' in browser.gui(panel).get("content", "")

            assert wait_until(lambda: shown("inactive"), 20.0, poll_s=0.02), browser.gui(panel)
            assert wait_until(lambda: browser.gui(plot).get("visible") is True, 10.0)

            def both_ports() -> bool:
                # One side's figures can be drawn a frame before the other's (seen once).
                shown("inactive")
                return browser.gui(panel)["content"].count('class="tr-tdpa-port"') == 2

            assert wait_until(both_ports, 20.0, poll_s=0.02), browser.gui(panel)
            assert "TDPA on — inactive" in browser.gui(panel)["content"]

            def plotted() -> bool:
                shown("inactive")
                data = browser.gui(plot).get("data")
                return data is not None and len(data) == 5 and len(data[0]) >= 2

            assert wait_until(plotted, 20.0, poll_s=0.02)
            assert wait_until(lambda: shown("active"), 20.0, poll_s=0.02), browser.gui(panel)
            assert 'data-acting="true"' in browser.gui(panel)["content"]

            # The figures stop (nobody engaged): the panel says so, the plot goes away.
            assert wait_until(
                lambda: 'data-tdpa="none"' in browser.gui(panel)["content"], FRESH_S + 10.0
            )
            assert wait_until(lambda: browser.gui(plot).get("visible") is False, 10.0)
        assert console.gui_errors == 0
    finally:
        console.close()


def test_no_nan_reaches_the_plot_rows() -> None:
    v = tdpa_view({"slave": PortSeen.first(fig("slave", e_in=0.1), 0.0)}, 0.0)
    assert all(math.isfinite(x) for x in plot_row(v))


def test_a_port_with_a_rotational_port_shows_its_energies() -> None:
    both = replace(fig("master", steps=1), rot_e_in=0.0125, rot_e_out=0.0031)
    v = tdpa_view({"master": PortSeen.first(both, 0.0)}, 0.1)
    m = v.port("master")
    assert m is not None and (m.rot_e_in_j, m.rot_e_out_j) == (0.0125, 0.0031)
    out = passivity_html(v)
    assert "rotation in (J)" in out and ">+0.0125<" in out
    assert "rotation out (J)" in out and ">+0.0031<" in out
    plain = passivity_html(tdpa_view({"master": PortSeen.first(fig("master"), 0.0)}, 0.1))
    assert "tr-tdpa-rot-in" not in plain  # no rotational port: no rows


def test_a_side_that_measured_the_round_trip_shows_it() -> None:
    timed = replace(fig("slave", steps=1), rtt_ms=412.25)
    v = tdpa_view({"slave": PortSeen.first(timed, 0.0)}, 0.1)
    s = v.port("slave")
    assert s is not None and s.rtt_ms == 412.25
    out = passivity_html(v)
    assert "round trip (ms)" in out and 'class="tr-tdpa-rtt"' in out and ">412.2<" in out
    plain = passivity_html(tdpa_view({"slave": PortSeen.first(fig("slave"), 0.0)}, 0.1))
    assert "tr-tdpa-rtt" not in plain  # nothing measured yet: no row
