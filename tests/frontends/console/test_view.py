"""The console's text panels: ids and data attributes for readers, and escaping."""

from __future__ import annotations

import html

from hypothesis import given
from hypothesis import strategies as st

from services.bus.messages import IDENTITY_R, Event, MasterState, RobotState
from services.frontends.console.view import (
    NO_ARM,
    ArmShown,
    MasterView,
    alive_html,
    estop_latched,
    events_html,
    loading_html,
    loading_items,
    status_html,
)

STATE = RobotState(
    seq=7,
    t_ns=1,
    status="ready",
    q=(0.0,) * 6,
    tool_p=(0.55, 0.0, 0.65),
    tool_R=IDENTITY_R,
    flange_p=(0.55, 0.0, 0.85),
    flange_R=IDENTITY_R,
    engage=0,
    cmd_seq=0,
)
MASTER = MasterState(
    seq=1,
    t_ns=1,
    master="console",
    engage=3,
    active=True,
    frame="world",
    scale_t=0.5,
    scale_r=1.0,
    hand_p=(0.0, 0.0, 0.0),
    hand_R=IDENTITY_R,
    device="virtual",
)


def _ev(kind: str, message: str, t_ns: int = 1_700_000_000_000_000_000) -> Event:
    return Event(seq=1, t_ns=t_ns, source="decision", kind=kind, message=message)


def test_status_panel_carries_ids_and_values() -> None:
    decision = {"mode": "follow", "estop": False, "lease": "console"}
    out = status_html(
        STATE, decision, None, MasterView("console", "engaged", MASTER, None), "home: done"
    )
    assert 'id="tr-robot-status" data-status="ready"' in out
    assert '<code id="tr-tool-p">+0.550 +0.000 +0.650</code>' in out
    assert 'data-mode="follow"' in out and 'data-lease="console"' in out
    assert 'data-link="engaged"' in out and "s_t 0.50" in out
    assert '<span id="tr-action">home: done</span>' in out
    assert "tr-estop" not in out


def test_status_panel_without_robot_or_decision() -> None:
    out = status_html(
        None, None, "decision: unavailable", MasterView("console", "waiting", None, "boom"), ""
    )
    assert 'data-status="none"' in out and 'data-mode="none"' in out
    assert "decision: unavailable" in out and "tr-master-error" in out


def test_the_arm_line_says_what_is_drawn_escaped() -> None:
    mview = MasterView("console", "waiting", None, None)
    none = status_html(None, None, None, mview, "")
    assert none == status_html(None, None, None, mview, "", NO_ARM)
    assert 'id="tr-arm" data-arm="none" data-model=""' in none and "no arm drawn" in none
    drawn = status_html(STATE, None, None, mview, "", ArmShown("visuals", "fr3", "fr3: 7 joints"))
    assert 'data-arm="visuals" data-model="fr3"' in drawn and "fr3: 7 joints" in drawn
    odd = status_html(None, None, None, mview, "", ArmShown("skeleton", '<b x="1">', "a<b"))
    assert "<b x" not in odd and "a&lt;b" in odd and 'data-model="&lt;b x=&quot;1&quot;&gt;"' in odd


def test_estop_is_shown() -> None:
    out = status_html(
        STATE,
        {"mode": "estop", "estop": True, "lease": None},
        None,
        MasterView("console", "holding", None, None),
        "",
    )
    assert 'id="tr-estop"' in out and 'data-lease=""' in out


def test_events_newest_first_with_kind() -> None:
    out = events_html([_ev("status", "first"), _ev("estop", "second")])
    assert out.index("second") < out.index("first")
    assert out.count('class="tr-event"') == 2 and 'data-kind="estop"' in out


def test_alive_lists_up_and_expected_down() -> None:
    out = alive_html(["arm", "console", "master/console"], expected=("arm", "vision"))
    assert 'data-alive="master/console"' in out and 'data-alive="arm"' in out
    assert 'data-down="vision"' in out and 'data-down="arm"' not in out


@given(st.text(max_size=200), st.text(max_size=50))
def test_bus_text_is_always_escaped(message: str, kind: str) -> None:
    """Whatever a peer puts in an event, the page gets text, never markup."""
    out = events_html([Event(seq=1, t_ns=1, source="x<y", kind=kind, message=message)])
    assert html.escape(message, quote=True) in out
    for dangerous in ("<script", "<img", "<b>", '"><'):
        if dangerous in message:
            assert out.count(dangerous) == 0


def test_a_ready_robot_is_not_green_while_the_estop_is_latched() -> None:
    mview = MasterView("console", "holding", None, None)
    clear = status_html(STATE, {"mode": "hold", "estop": False}, None, mview, "")
    latched = status_html(STATE, {"mode": "estop", "estop": True}, None, mview, "")
    assert 'data-status="ready" data-estop="clear" style="color:#1a7f37"' in clear
    assert 'data-status="ready" data-estop="latched" style="color:#cf222e"' in latched
    assert "held by the e-stop" in latched and "held by the e-stop" not in clear
    assert 'id="tr-estop"' in latched


def test_estop_latched_reads_only_a_true_latch() -> None:
    assert estop_latched({"estop": True})
    assert not estop_latched({"estop": False})
    assert not estop_latched({"estop": "yes"})  # not a bool: not believed
    assert not estop_latched(None)


def test_loading_lists_what_has_not_arrived_and_ignores_absent_services() -> None:
    assert loading_items(state=False, decision=False, force=None, video=None) == (
        "robot state",
        "supervisor",
    )
    assert loading_items(state=True, decision=True, force=False, video=False) == (
        "force",
        "video",
    )
    assert loading_items(state=True, decision=True, force=True, video=None) == ()
    out = loading_html(("robot state", "video"))
    assert 'data-waiting="robot state,video"' in out and "waiting for robot state, video" in out
    assert loading_html(()) == '<div id="tr-loading" data-waiting=""></div>'
