"""`telerobot bench passivity --link`'s document: the simulated bench's keys and table from
runs over the link (the runs themselves are faked here; test_link_loop.py runs one for
real)."""

from __future__ import annotations

import json
import math
from typing import Any

import pytest

from services.bus.messages import Event, MasterFeedback
from services.tools.tdpa import link_bench, sim_bench


def fake_run(rtt_ms: float, on: bool, *_: object, **__: object) -> dict[str, Any]:
    m: dict[str, Any] = {
        "peak_n": 90.0 + rtt_ms / 100,
        "steady_n": 8.0,
        "felt_n": 6.5 if on else 7.5,
        "rms_n": 0.4 if on else 4.0,
        "swing_n": 0.3 if on else 3.5,
        "held": True,
        "creep_n_s": 0.5 if on else 3.0,
        "penetration_mm": 2.5,
        "rtt_ms": rtt_ms,
        "passivity": on,
        "emulator": "delayline",
        "force": [[0.0, 0.0], [0.1, 1.0]],
        "events": ["decision/limit: x"],
    }
    nan = math.nan
    m |= {
        "master_in_j": 0.1 if on else nan,
        "master_out_j": 0.05 if on else nan,
        "slave_in_j": 0.05 if on else nan,
        "slave_out_j": 0.35 if on else nan,
        "slave_recovered_j": 0.25,
        "master_dissipated_j": 0.01 if on else nan,
        "slave_dissipated_j": 0.02 if on else nan,
        "slave_rtt_ms": 1.5 * rtt_ms + 1.0 if on else nan,
        "master_rtt_ms": 1.5 * rtt_ms + 2.0 if on else nan,
        "uplink_ms": 0.75 * rtt_ms if on else nan,
        "uplink_p90_ms": rtt_ms if on else nan,
    }
    return m


def test_measures_count_what_the_workcell_gave_back_as_input() -> None:
    got = link_bench.bench_measures(fake_run(200.0, True))
    # out 0.05 + 0.35 against in 0.1 + 0.05 + 0.25 given back: nothing generated
    assert got["energy_generated_j"] == pytest.approx(0.0, abs=1e-12)
    assert got["stable"] is True  # swing 4 % of the steady force
    m = fake_run(200.0, True) | {"slave_out_j": 0.45}
    assert link_bench.bench_measures(m)["energy_generated_j"] == pytest.approx(0.1)
    off = link_bench.bench_measures(fake_run(200.0, False))
    assert math.isnan(off["energy_generated_j"]) and off["stable"] is False  # swing 44 %


@pytest.mark.parametrize(
    ("steady", "rms", "swing", "hold", "stable", "settled"),
    [
        (10.0, 0.5, 0.5, True, True, True),
        (10.0, 1.0, 1.0, True, False, False),
        (10.0, 2.0, 0.3, True, True, False),  # a step inside the window: no oscillation
        (13.2, 19.4, 0.7, False, False, False),  # 0 -> 42 N once in the window: a bounce
        (0.5, 0.0, 0.0, True, False, False),
        (37.9, 0.1, 0.1, True, True, True),
        (38.0, 0.1, 0.1, True, False, False),
        (42.0, 0.02, 0.02, True, False, False),
    ],
)
def test_a_calm_rest_on_the_supervisors_limit_is_not_stable(
    steady: float, rms: float, swing: float, hold: bool, stable: bool, settled: bool
) -> None:
    """Stable means the contact held through the window and a swing (RMS about the best
    monotone fit) < 10 % of a steady force between 1 N and 95 % of the decision's 40 N
    contact limit: at the limit the supervisor holds the tool, the loop did not settle.
    Settled asks the RMS about the mean to be < 10 % of such a force."""
    assert link_bench.SUPERVISOR_LIMIT_N == 40.0
    m = fake_run(700.0, False) | {"steady_n": steady, "rms_n": rms, "swing_n": swing}
    m["held"] = hold
    got = link_bench.bench_measures(m)
    assert (got["stable"], got["settled"]) == (stable, settled)


def test_matrix_document_has_the_simulated_bench_keys(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(link_bench, "run_over_link", fake_run)
    said: list[str] = []
    doc, runs = link_bench.run_matrix((0, 700), 0.1, 0.01, said.append, transport="udp")
    assert sorted(runs) == [(0, False), (0, True), (700, False), (700, True)]
    assert len(said) == 6  # each run, and what the ports measured in each with TDPA on
    assert "decision 1051.0 ms, master 1052.0 ms" in said[5]
    assert "on the way 525.0 ms (p90 700.0)" in said[5]
    for delay in (0, 700):
        for on in ("off", "on"):
            for name in sim_bench.MEASURES:
                assert f"passivity_{delay}_{on}_{name}" in doc
    assert doc["passivity_700_on_peak_force_n"] == pytest.approx(97.0)
    assert doc["passivity_700_off_creep_n_s"] == pytest.approx(3.0)
    assert doc["passivity_700_on_felt_force_n"] == pytest.approx(6.5)
    assert doc["passivity_700_off_energy_generated_j"] is None  # not observed: null, not NaN
    assert doc["settings"]["emulator"] == "delayline"
    assert doc["settings"]["transport"] == "udp"
    assert sorted(doc["runs"]) == ["0_off", "0_on", "700_off", "700_on"]
    assert doc["runs"]["700_on"]["events"] == ["decision/limit: x"]
    assert doc["runs"]["700_on"]["measured_rtt_ms"] == {"decision": 1051.0, "master": 1052.0}
    assert doc["runs"]["700_off"]["measured_rtt_ms"] == {"decision": None, "master": None}
    json.loads(json.dumps(doc, allow_nan=False))  # strict JSON
    text = sim_bench.table(doc)
    assert len(text.splitlines()) == 2 + 4
    assert "–" in text.splitlines()[2]  # the off row's energy


def test_the_matrix_runs_the_arm_it_is_given(monkeypatch: pytest.MonkeyPatch) -> None:
    """`--link --model`: every run of the matrix presses with that arm, and the document and
    its model line say which."""
    models: list[object] = []

    def run(rtt_ms: float, on: bool, *a: object, **kw: object) -> dict[str, Any]:
        models.append(kw.get("model"))
        return fake_run(rtt_ms, on)

    monkeypatch.setattr(link_bench, "run_over_link", run)
    doc, _ = link_bench.run_matrix((0, 50), 0.1, 0.01, lambda _: None, model="fr3")
    assert models == ["fr3"] * 4
    assert doc["settings"]["model"] == "fr3"
    assert "the arm (fr3) on the MuJoCo cell" in link_bench.model_line(doc)
    assert "friction shown × 1" in link_bench.model_line(doc)


def test_the_matrix_shows_the_friction_it_is_told(monkeypatch: pytest.MonkeyPatch) -> None:
    """`--link --tangential-gain`: every run's master shows that share of the friction."""
    gains: list[object] = []

    def run(rtt_ms: float, on: bool, *a: object, **kw: object) -> dict[str, Any]:
        gains.append(kw.get("tangential_gain"))
        return fake_run(rtt_ms, on)

    monkeypatch.setattr(link_bench, "run_over_link", run)
    doc, _ = link_bench.run_matrix((200,), 0.1, 0.01, lambda _: None, tangential_gain=0.0)
    assert gains == [0.0, 0.0]
    assert doc["settings"]["tangential_gain"] == 0.0
    assert "friction shown × 0" in link_bench.model_line(doc)


def test_link_run_says_why_not_where_the_link_cannot_be_made(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(link_bench, "unavailable", lambda: "needs root")
    out = tmp_path / "link.json"
    assert sim_bench.main(["--link", "--json", str(out), "--plots", ""]) == 2
    assert "needs root" in capsys.readouterr().err
    assert not out.exists()


def test_link_run_writes_its_own_document_and_plots(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(link_bench, "unavailable", lambda: None)
    monkeypatch.setattr(link_bench, "run_over_link", fake_run)
    out = tmp_path / "link.json"
    argv = ["--link", "--delays-ms", "0,200", "--json", str(out), "--plots", str(tmp_path)]
    assert sim_bench.main(argv) == 0
    doc = json.loads(out.read_text())
    assert doc["passivity_200_on_steady_force_n"] == pytest.approx(8.0)
    assert sorted(p.name for p in tmp_path.glob("*.png")) == [
        "passivity_link_0ms.png",
        "passivity_link_200ms.png",
    ]
    said = capsys.readouterr().out
    assert "RTT ms" in said
    # The table says what it is of: the services over the link, not the simulated loop.
    lines = said.splitlines()
    model = lines[next(i for i, x in enumerate(lines) if "RTT ms" in x) - 1]
    assert model.startswith("Model: the real services over a real link"), model
    assert "MuJoCo" in model and "500 Hz" in model and "round trips [0, 200] ms" in model
    assert f"contact damping {link_bench.CONTACT_DAMPING_NS_M:g} N·s/m" in model
    assert "simulated 1-DoF" not in said and "None" not in model
    assert doc["settings"]["contact_damping_ns_m"] == link_bench.CONTACT_DAMPING_NS_M


def _runs_told(monkeypatch: pytest.MonkeyPatch, keyword: str) -> list[object]:
    """What each (faked) run over the link is given as `keyword`, in order."""
    monkeypatch.setattr(link_bench, "unavailable", lambda: None)
    told: list[object] = []

    def run(rtt_ms: float, on: bool, *a: object, **kw: object) -> dict[str, Any]:
        told.append(kw.get(keyword))
        return fake_run(rtt_ms, on)

    monkeypatch.setattr(link_bench, "run_over_link", run)
    return told


@pytest.mark.parametrize(
    ("flag", "keyword", "value", "default", "told_as"),
    [
        ("--approach-zone", "approach_zone_m", 0.0, link_bench.APPROACH_ZONE_M, None),
        ("--rate-mbit", "rate_mbit", 0.5, 0.0, None),
        ("--master-rate-hz", "master_rate_hz", 200.0, link_bench.MASTER_RATE_HZ, "rate_hz"),
        ("--hold-s", "hold_s", 4.0, link_bench.HOLD_S, None),
        ("--yield", "yield_m_s_n", 0.0, link_bench.YIELD_DEFAULT, None),
    ],
)
def test_a_link_setting_reaches_every_run_and_the_document(
    monkeypatch: pytest.MonkeyPatch,
    tmp_path: Any,
    flag: str,
    keyword: str,
    value: float,
    default: float,
    told_as: str | None,
) -> None:
    """`keyword` in the document's settings; `told_as` (default: the same) in each run."""
    told = _runs_told(monkeypatch, told_as or keyword)
    out = tmp_path / "link.json"
    base = ["--link", "--delays-ms", "50", "--json", str(out), "--plots", ""]
    assert sim_bench.main(base) == 0
    assert told == [default, default]
    assert json.loads(out.read_text())["settings"][keyword] == default
    told.clear()
    assert sim_bench.main([*base, flag, str(value)]) == 0
    assert told == [value, value]
    assert json.loads(out.read_text())["settings"][keyword] == value


@pytest.mark.parametrize(
    "argv",
    [
        ["--approach-zone", "0.02"],
        ["--link", "--approach-zone", "-1"],
        ["--rate-mbit", "1"],
        ["--link", "--rate-mbit", "0.01"],
        ["--link", "--rate-mbit", "-2"],
        ["--master-rate-hz", "500"],
        ["--link", "--master-rate-hz", "5"],
        ["--link", "--master-rate-hz", "1e308"],
        ["--hold-s", "4"],
        ["--link", "--hold-s", "0.5"],
        ["--link", "--hold-s", "nan"],
        ["--yield", "5e-5"],
        ["--link", "--yield", "-1e-5"],
        ["--link", "--yield", "0.5"],
        ["--link", "--yield", "nan"],
    ],
)
def test_a_bad_link_setting_is_refused_by_name(
    argv: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    """Without --link, or out of its range (a float can be valid and absurd): exit 2, and
    the message names the flag."""
    with pytest.raises(SystemExit) as e:
        sim_bench.main(argv)
    assert e.value.code == 2
    assert argv[-2] in capsys.readouterr().err


def test_the_force_felt_is_the_mean_shown_on_the_hand_over_the_hold() -> None:
    """`master/feedback` as the console receives it: only the samples inside the window
    count, and the master frame's z (the press) is what the hand feels."""
    trace = link_bench.Trace()
    t0 = 10**12
    for k, fz in enumerate([30.0, 4.0, 6.0, 8.0, 50.0]):  # one before, three in, one after
        trace.on_feedback(
            MasterFeedback(
                seq=k + 1,
                t_ns=t0 + int((1.0 + k) * 1e9),
                master="op",
                f=(0.5, 0.0, fz),
                c=(0.0, 0.0, 0.0),
                saturated=False,
                stale=False,
            )
        )
    m = link_bench.metrics(trace, t0, 2.0, 5.0)
    assert m["felt_n"] == pytest.approx(6.0)
    assert link_bench.metrics(link_bench.Trace(), t0, 2.0, 5.0)["felt_n"] == 0.0


def test_events_after_the_operators_last_figures_are_the_ends_not_the_runs(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The decision's hold when the finished operator's token goes is teardown: the run's
    events are those up to the master's last figures (seen in the suite's link test: a
    `watchdog` event counted as a hold during the press)."""
    clock = iter([10.0, 20.0])
    monkeypatch.setattr(link_bench.time, "monotonic", lambda: next(clock))
    trace = link_bench.Trace()
    trace.on_event(Event(seq=1, t_ns=1, source="decision", kind="limit", message="zone"))
    trace.master_rx_s = 15.0  # the master's last figures arrived between the two
    trace.on_event(Event(seq=2, t_ns=2, source="decision", kind="watchdog", message="lost"))
    assert trace.events_split() == (["decision/limit: zone"], ["decision/watchdog: lost"])
    trace.master_rx_s = 0.0  # no figures yet: all of it is the run's
    assert trace.events_split() == (["decision/limit: zone", "decision/watchdog: lost"], [])


@pytest.mark.parametrize("transport", ["tls", "quic", "quic-mixed"])
def test_the_link_runs_on_the_quic_profile_too(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Any, transport: str
) -> None:
    """`--transport quic-mixed` (issue 41: TDPA's link bench on the QUIC profile) reaches
    every run and the document; the run itself dials the QUIC listener with its metadata."""
    told = _runs_told(monkeypatch, "transport")
    out = tmp_path / "link.json"
    argv = ["--link", "--delays-ms", "50", "--json", str(out), "--plots", ""]
    assert sim_bench.main([*argv, "--transport", transport]) == 0
    assert told == [transport, transport]
    assert json.loads(out.read_text())["settings"]["transport"] == transport
    from services.tools.tdpa.transports import endpoint

    assert endpoint(transport, "10.203.0.1", 1).startswith(transport.split("-")[0] + "/")
