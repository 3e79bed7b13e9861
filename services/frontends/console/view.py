"""The console's text panels as HTML: robot and supervisor status, master, services, events,
time-domain passivity.

Pure functions of what the bus delivered, so they are tested without a browser. Every value
that came off the bus is escaped. Elements carry stable ids (`tr-…`) and `data-` attributes
so tests and scripts can read the page.
"""

from __future__ import annotations

import html
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from services.bus.messages import Event, MasterState, RobotState
from services.frontends.console.tdpa import PortFigures, TdpaView

#: services the console expects on a complete system (alive/<name>)
EXPECTED_SERVICES: tuple[str, ...] = ("arm", "force", "decision", "vision")

_STATUS_COLOR = {
    "ready": "#1a7f37",
    "moving": "#0969da",
    "initializing": "#9a6700",
    "connected": "#9a6700",
    "disconnected": "#6e7781",
    "error": "#cf222e",
}
_ESTOP_COLOR = "#cf222e"
_ARM_COLOR = {"visuals": "#24292f", "invalid": _ESTOP_COLOR}
"""The arm row's colour by what is drawn; amber otherwise (none yet, or the skeleton)."""
_KIND_COLOR = {
    "estop": "#cf222e",
    "error": "#cf222e",
    "watchdog": "#bc4c00",
    "limit": "#bc4c00",
    "contact": "#bc4c00",
    "rejected": "#bc4c00",
    "lease": "#8250df",
    "status": "#0969da",
}


@dataclass(frozen=True, slots=True)
class ArmShown:
    """What the 3D view draws of the arm: `kind` is `none` (no robot/arm/description yet:
    no arm drawn), `visuals` (the URDF's), `skeleton` (its visuals cannot be drawn here) or
    `invalid` (the description does not build); `model` its name; `text` a line for people."""

    kind: str
    model: str
    text: str


NO_ARM = ArmShown("none", "", "no robot/arm/description yet: no arm drawn")


@dataclass(frozen=True, slots=True)
class MasterView:
    """What the console knows about the master it drives."""

    master_id: str
    link: str
    """The gizmo link's state: `engaged`, `master-shift`, `holding`, `waiting`, …"""
    state: MasterState | None
    error: str | None


def _e(x: object) -> str:
    return html.escape(str(x), quote=True)


def _vec(v: Iterable[float], digits: int = 3) -> str:
    return " ".join(f"{x:+.{digits}f}" for x in v)


def _row(label: str, value_html: str) -> str:
    return (
        f'<tr><td style="color:#57606a;padding-right:8px;white-space:nowrap">{_e(label)}</td>'
        f"<td>{value_html}</td></tr>"
    )


def status_html(
    state: RobotState | None,
    decision: Mapping[str, Any] | None,
    decision_error: str | None,
    master: MasterView,
    last_action: str,
    arm: ArmShown = NO_ARM,
) -> str:
    """The status panel: robot (robot/state), the arm drawn (robot/arm/description),
    supervisor (decision `status`), master, and the result of the last button pressed."""
    rows: list[str] = []
    latched = estop_latched(decision)
    if state is None:
        rows.append(_row("robot", '<span id="tr-robot-status" data-status="none">no state</span>'))
    else:
        # A latched e-stop holds the arm whatever its own status says: "ready" is not shown
        # as ready (green) until the latch is reset.
        color = _ESTOP_COLOR if latched else _STATUS_COLOR.get(state.status, "#24292f")
        held = " — held by the e-stop" if latched else ""
        rows.append(
            _row(
                "robot",
                f'<b id="tr-robot-status" data-status="{_e(state.status)}" '
                f'data-estop="{"latched" if latched else "clear"}" '
                f'style="color:{color}">{_e(state.status)}{held}</b>',
            )
        )
        rows.append(
            _row("tool p (m)", f'<code id="tr-tool-p">{_vec(state.tool_p)}</code>'),
        )
        rows.append(_row("q (rad)", f'<code id="tr-q">{_vec(state.q, 2)}</code>'))
    color = _ARM_COLOR.get(arm.kind, "#9a6700")
    rows.append(
        _row(
            "arm",
            f'<span id="tr-arm" data-arm="{_e(arm.kind)}" data-model="{_e(arm.model)}" '
            f'style="color:{color}">{_e(arm.text)}</span>',
        )
    )
    if decision is not None:
        mode = str(decision.get("mode", "?"))
        estop = bool(decision.get("estop"))
        lease = decision.get("lease")
        mode_html = f'<b id="tr-mode" data-mode="{_e(mode)}">{_e(mode)}</b>'
        if estop:
            mode_html += ' <b id="tr-estop" style="color:#cf222e">E-STOP LATCHED</b>'
        rows.append(_row("supervisor", mode_html))
        rows.append(
            _row(
                "lease",
                f'<span id="tr-lease" data-lease="{_e(lease or "")}">'
                f"{_e(lease) if lease else 'free'}</span>",
            )
        )
    else:
        rows.append(
            _row(
                "supervisor",
                f'<span id="tr-mode" data-mode="none" style="color:#cf222e">'
                f"{_e(decision_error or 'no reply yet')}</span>",
            )
        )
    rows.append(_row("master", master_html(master)))
    rows.append(_row("last action", f'<span id="tr-action">{_e(last_action or "-")}</span>'))
    return f'<table style="font-size:0.8em;width:100%">{"".join(rows)}</table>'


def estop_latched(decision: Mapping[str, Any] | None) -> bool:
    """Whether the decision server's `status` reports its e-stop latched."""
    return decision is not None and decision.get("estop") is True


VIDEO_STYLE = (
    "<style>"
    # viser draws a GUI image at most its own size (max-width: 100%), so a small frame, as
    # the camera sends while its link is congested (160×120 an eye), would shrink in its
    # window; it is scaled up by the browser instead (nothing more crosses the link). The
    # video is the console's only GUI image, and viser's images are blob: URLs.
    'img[src^="blob:"]{width:100%;height:auto}'
    "</style>"
)
"""The video window's style: the image fills the window's width whatever the frame's size,
keeping its aspect."""


def loading_items(
    state: bool,
    decision: bool,
    force: bool | None,
    video: bool | None,
) -> tuple[str, ...]:
    """What the page still waits for, in the order it usually arrives: the robot's state
    (the 3D mirror), the supervisor's first reply, the force (None: no force service to
    wait for) and the video (None: no vision, or the view is off). True = arrived."""
    items = (
        ("robot state", state),
        ("supervisor", decision),
        ("force", force),
        ("video", video),
    )
    return tuple(name for name, have in items if have is False)


def loading_html(waiting: Sequence[str]) -> str:
    """The loading indicator: what the page still waits for (empty when nothing)."""
    if not waiting:
        return '<div id="tr-loading" data-waiting=""></div>'
    return (
        f'<div id="tr-loading" data-waiting="{_e(",".join(waiting))}" '
        'style="font-size:0.85em;padding:6px 8px;border-radius:6px;background:#fff8c5;'
        'color:#7d4e00">⏳ loading: waiting for '
        f"{_e(', '.join(waiting))}…</div>"
    )


def master_html(m: MasterView) -> str:
    """One line: the master's id, device, link state, scales and frame."""
    parts = [f'<span id="tr-master" data-link="{_e(m.link)}">{_e(m.master_id)}: {_e(m.link)}']
    st = m.state
    if st is not None:
        parts.append(
            f" ({_e(st.device)}, {_e(st.frame)}, s_t {st.scale_t:.2f}, s_r {st.scale_r:.2f})"
        )
    parts.append("</span>")
    if m.error:
        parts.append(f'<br><span id="tr-master-error" style="color:#cf222e">{_e(m.error)}</span>')
    return "".join(parts)


def alive_html(names: Iterable[str], expected: Sequence[str] = EXPECTED_SERVICES) -> str:
    """The services whose liveliness token is up; expected ones that are down in red."""
    up = sorted(set(names))
    items = [f'<li data-alive="{_e(n)}" style="color:#1a7f37">● {_e(n)}</li>' for n in up] + [
        f'<li data-down="{_e(n)}" style="color:#cf222e">○ {_e(n)} (down)</li>'
        for n in expected
        if n not in up
    ]
    return (
        '<ul id="tr-alive" style="font-size:0.8em;list-style:none;padding-left:0;margin:0">'
        + "".join(items)
        + "</ul>"
    )


def events_html(events: Sequence[Event]) -> str:
    """The event log, newest first: time, source, kind, message."""
    items = []
    for ev in reversed(events):
        t = time.strftime("%H:%M:%S", time.localtime(ev.t_ns / 1e9))
        ms = (ev.t_ns // 1_000_000) % 1000
        color = _KIND_COLOR.get(ev.kind, "#24292f")
        items.append(
            f'<li class="tr-event" data-kind="{_e(ev.kind)}" data-source="{_e(ev.source)}">'
            f'<span style="color:#8c959f">{t}.{ms:03d}</span> '
            f'<b style="color:{color}">{_e(ev.kind)}</b> '
            f'<span style="color:#57606a">{_e(ev.source)}</span> {_e(ev.message)}</li>'
        )
    return (
        '<ul id="tr-events" style="font-size:0.75em;list-style:none;padding-left:0;margin:0;'
        'max-height:18em;overflow-y:auto">' + "".join(items) + "</ul>"
    )


_TDPA = {
    "none": ("#6e7781", "passivity off — no TDPA figures (off, or nobody engaged)"),
    "observing": ("#57606a", "TDPA observing only (controllers off)"),
    "inactive": ("#1a7f37", "TDPA on — inactive (the channel is passive)"),
    "active": ("#bc4c00", "TDPA ACTIVE — dissipating energy"),
}
_ACTION = {"master": ("β", "N·s/m"), "slave": ("α", "m/N")}


def _joules(x: float | None) -> str:
    return "-" if x is None else f"{x:+.4f}"


def _port_html(p: PortFigures) -> str:
    symbol, unit = _ACTION[p.side]
    color = "#bc4c00" if p.acting and p.enabled else "#24292f"
    remote = "slave" if p.side == "master" else "master"
    cells: list[tuple[str, str, str]] = [
        ("in (J)", "tr-tdpa-in", _joules(p.e_in_j)),
        ("out (J)", "tr-tdpa-out", _joules(p.e_out_j)),
        (f"{remote} in (J)", "tr-tdpa-remote", _joules(p.remote_in_j)),
        ("reservoir (J)", "tr-tdpa-reservoir", _joules(p.reservoir_j)),
        (f"{symbol} ({unit})", "tr-tdpa-gain", f"{p.gain:.3g}"),
        ("dissipated (J)", "tr-tdpa-dissipated", _joules(p.dissipated_j)),
        ("acted (steps)", "tr-tdpa-steps", str(p.active_steps)),
    ]
    if p.asked_n is not None and p.shown_n is not None:
        # What the controller withholds from the hand, at the tool (docs/passivity.md).
        felt = f"{p.shown_n:.2f} of {p.asked_n:.2f}"
        cells.append(("hand feels (N)", "tr-tdpa-felt", felt))
    if p.repaid_j is not None and p.forgiven_j is not None:
        # An impact's overdraw: repaid by the workcell, or forgiven (created by the channel).
        cells.append(("overdraw repaid (J)", "tr-tdpa-repaid", _joules(p.repaid_j)))
        cells.append(("forgiven (J)", "tr-tdpa-forgiven", _joules(p.forgiven_j)))
    if p.rot_e_in_j is not None and p.rot_e_out_j is not None:
        # The rotational port's own energies (moment × rotation), beside the force's.
        cells.append(("rotation in (J)", "tr-tdpa-rot-in", _joules(p.rot_e_in_j)))
        cells.append(("rotation out (J)", "tr-tdpa-rot-out", _joules(p.rot_e_out_j)))
    if p.rtt_ms is not None:
        # What the loop really waits for: the link and whatever queued on it.
        cells.append(("round trip (ms)", "tr-tdpa-rtt", f"{p.rtt_ms:.1f}"))
    rows = "".join(
        _row(label, f'<code class="{cls}" style="color:{color}">{_e(v)}</code>')
        for label, cls, v in cells
    )
    head = (
        f'<b>{_e(p.side)} port</b> <span style="color:#57606a">{_e(p.master)} #{p.engage}'
        f"{'' if p.enabled else ', observing'}</span>"
    )
    return (
        f'<div class="tr-tdpa-port" data-side="{_e(p.side)}" '
        f'data-acting="{str(p.acting and p.enabled).lower()}" '
        f'data-reservoir="{p.reservoir_j!r}" data-gain="{p.gain!r}">{head}'
        f'<table style="font-size:1em;width:100%">{rows}</table></div>'
    )


def passivity_html(view: TdpaView) -> str:
    """The TDPA panel: a one-line indicator (`data-tdpa` none | observing | inactive |
    active), then per port its energies, reservoir and the controller's action."""
    state = view.state
    color, text = _TDPA[state]
    head = (
        f'<div id="tr-tdpa" data-tdpa="{state}" style="color:{color};font-weight:600">'
        f"{_e(text)}</div>"
    )
    return (
        f'<div style="font-size:0.8em">{head}'
        + "".join(_port_html(p) for p in view.ports)
        + "</div>"
    )
