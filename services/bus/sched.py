"""The telerobot session's share of the CPU on a busy host (issue 42 item 5).

Linux's autogroup scheduling (`kernel.sched_autogroup_enabled`, on by default on desktop
and many server kernels) shares the CPU fairly between *sessions* first: `nice` counts
only within one. A compile started at nice 19 in another terminal (its own session) then
weighs as much as the whole telerobot session, whose control loops (a 100 Hz master, the
decision's 100 ms watchdog, the arm's servo) wait behind it for tens of milliseconds at a
time on a 2-core host. Measured with `telerobot bench` (phase `busy_host`, docs/bench.md).

`claim_cpu_share()` sets the session's autogroup nice to AUTOGROUP_NICE, which gives it
the weight it would have had if nice counted across sessions. It needs CAP_SYS_NICE (root,
or `AmbientCapabilities=CAP_SYS_NICE` in a systemd unit, `cap_add: [SYS_NICE]` in compose:
the force service's have it); without it the service runs as before and says so once.
Every service calls it at start-up (`run_service`), and so does `telerobot up`, whose
children share its session.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

AUTOGROUP_NICE = -10
"""Weight ≈ 9.3 × a nice-0 group (the kernel's table): a nice-19 job in another session
keeps its ~10 % of a core, the control loops get what they need."""
AUTOGROUP = Path("/proc/self/autogroup")
OPT_OUT = "TELEROBOT_CPU_SHARE"
"""Set to `off` to leave the session's share alone (an A/B, or a host that manages it)."""

log = logging.getLogger("telerobot.sched")


def claim_cpu_share(path: Path = AUTOGROUP, nice: int = AUTOGROUP_NICE) -> str:
    """Raise this session's autogroup weight; what happened, in words: `raised`,
    `already` (at or below `nice`), `absent` (no autogroup on this kernel), or `refused …`
    (no CAP_SYS_NICE: logged as a warning with the fix), `off` (TELEROBOT_CPU_SHARE=off)."""
    if os.environ.get(OPT_OUT, "").lower() == "off":
        return "off"
    try:
        text = path.read_text()  # "/autogroup-870 nice 0"
        current = int(text.split()[-1])
    except (OSError, ValueError, IndexError):
        return "absent"
    if current <= nice:
        return "already"
    try:
        path.write_text(f"{nice}\n")
    except OSError as e:
        why = f"refused ({e.strerror or e})"
        log.warning(
            "could not raise the session's CPU share (autogroup nice %d → %d: %s): on a busy "
            "host the control loops may wait behind other work; run with CAP_SYS_NICE "
            "(systemd AmbientCapabilities, compose cap_add) or keep the host quiet",
            current,
            nice,
            why,
        )
        return why
    log.debug("session CPU share raised: autogroup nice %d → %d", current, nice)
    return "raised"
