"""Notes for people at the end of a run: where force samples went missing, and which
phases shared the machine with other processes."""

from __future__ import annotations

from typing import Any


def force_note(phases: dict[str, Any]) -> str:
    """Where force samples went missing: the sensor's own rate beside the delivered one, and
    the missing seqs beside those the force service itself dropped (0 with its default
    inline publishing; its optional hand-off queue keeps the newest when its publisher
    falls behind)."""
    parts, missing = [], []
    for key, name in (
        ("force_alone", "alone"),
        ("force_stereo_paper", "with 360×288"),
        ("force_stereo_vga", "with 640×480"),
    ):
        f = phases.get(key)
        if f is None:
            continue
        parts.append(f"{name} {f['produced_rate_hz']:.0f}/{f['rate_hz']:.0f} Hz")
        lost = int(f["loss"]["lost"])
        if lost:
            drops = (f.get("service") or {}).get("drops")
            inside = f" ({drops} dropped inside the force service)" if drops is not None else ""
            missing.append(f"{name} {lost} missing{inside}")
    text = "force produced by the sensor / received by the bench: " + ", ".join(parts)
    if parts and not missing:
        return text + "; 0 lost: every sample the sensor produced arrived."
    return text + "; " + ", ".join(missing) + "."


BUSY_SHARE = 0.15
"""Above this share of the CPUs taken by other processes, a phase is reported as contended."""


def busy_note(cpu_use: dict[str, Any]) -> str | None:
    """A plain warning naming the phases during which other processes took more than
    BUSY_SHARE of the CPUs (their figures include that contention)."""
    run = cpu_use.get("run")
    phases = cpu_use.get("phases", {})
    busy = {k: v["others_share"] for k, v in phases.items() if v["others_share"] > BUSY_SHARE}
    if run is None or not busy:
        return None
    listed = ", ".join(f"{k} {share:.0%}" for k, share in busy.items())
    return (
        f"the machine was shared: other processes took {run['others_share']:.0%} of the "
        f"{run['cpus']} CPUs over the run, and more than {BUSY_SHARE:.0%} during: {listed}; "
        "those figures include that contention."
    )
