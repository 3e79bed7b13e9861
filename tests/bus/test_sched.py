"""The session's CPU share (services.bus.sched): the autogroup nice is lowered to
AUTOGROUP_NICE, never raised, and a refusal is said with its fix."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from services.bus.sched import AUTOGROUP_NICE, claim_cpu_share


def test_the_autogroup_nice_is_lowered_once_and_never_raised(tmp_path: Path) -> None:
    group = tmp_path / "autogroup"
    group.write_text("/autogroup-870 nice 0\n")
    assert claim_cpu_share(group) == "raised"
    assert group.read_text().strip() == str(AUTOGROUP_NICE)
    group.write_text(f"/autogroup-870 nice {AUTOGROUP_NICE - 5}\n")
    assert claim_cpu_share(group) == "already"  # someone set it higher: left alone
    assert group.read_text().split()[-1] == str(AUTOGROUP_NICE - 5)


def test_no_autogroup_is_nothing_to_do(tmp_path: Path) -> None:
    assert claim_cpu_share(tmp_path / "absent") == "absent"
    garbage = tmp_path / "garbage"
    garbage.write_text("not a nice value")
    assert claim_cpu_share(garbage) == "absent"


def test_a_refusal_is_a_warning_naming_the_capability(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    group = tmp_path / "ro"
    group.mkdir()
    ro = group / "autogroup"
    ro.write_text("/autogroup-1 nice 0\n")

    class ReadOnly(type(ro)):  # type: ignore[misc]
        def write_text(self, *a: object, **k: object) -> int:
            raise PermissionError(1, "Operation not permitted")

    with caplog.at_level(logging.WARNING, logger="telerobot.sched"):
        got = claim_cpu_share(ReadOnly(ro))
    assert got.startswith("refused") and "not permitted" in got
    assert any("CAP_SYS_NICE" in r.getMessage() for r in caplog.records)


def test_the_opt_out_leaves_it_alone(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    group = tmp_path / "autogroup"
    group.write_text("/autogroup-870 nice 0\n")
    monkeypatch.setenv("TELEROBOT_CPU_SHARE", "off")
    assert claim_cpu_share(group) == "off"
    assert group.read_text().split()[-1] == "0"
