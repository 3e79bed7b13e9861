"""`telerobot bench passivity`: the contact task over a bad link, TDPA off and on.

The simulated operator presses the tool onto a stiff surface, holds and releases
(`services.tools.tdpa.loop`), at round-trip delays 0, 50, 200 and 700 ms with 10 % jitter and
1 % loss by default. Per run: peak and steady contact force, the force felt (the mean
displayed on the hand over the same window as the steady force), oscillation (RMS of the force
about its mean after settling), swing (its RMS about its best monotone fit over the same
window: the back-and-forth, which a step or a climb of the contact is not), creep (the
force's least-squares slope over the same window, N/s: a climb the RMS also counts),
penetration, the energy balance (the most the channel's observed output ever exceeded its
input) and what each controller dissipated; stable (swing below 10 % of the steady force:
no sustained oscillation) and settled (the RMS below 10 %: no step in the window either).
One table,
one JSON (keys `passivity_<delay_ms>_<on|off>_<measure>`), one plot per delay (contact force
over time, off and on). "on" is both ports with the master's energy-bounding force limiter
(`--no-master-limit`: the damper alone). `--seeds N` also runs seeds 1 … N (each its own
jitter and losses) and sums them up per delay (`seeds`). `--twist` adds a turn against a
torsional stop to the press (3-DoF, the services' ports, a rotational port at each end): the
same measures of the moment under `passivity_<delay_ms>_<on|off>_moment_<measure>` (N·m;
`penetration_mm` is then mrad past the stop). docs/passivity.md.

The link here is the simulation's own (seeded, deterministic, no processes). `--link` runs
the same task through the real services over a real bad link instead (network namespaces,
`services.tools.tdpa.netem`; needs root; about 20 s per run): `services.tools.tdpa.
link_bench`, its own JSON with the same keys and one plot per delay.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from services.control.arm.model import DEFAULT_MODEL, SHIPPED
from services.control.passivity.dynamics import Wall
from services.tools.tdpa.loop import (
    SLAVE_SPEED_M_S,
    LoopResult,
    LoopSpec,
    Twist,
    contact_metrics,
    simulate,
    twist_metrics,
)
from services.tools.tdpa.results import off_on_plot, put_measures

DEFAULT_DELAYS_MS = (0, 50, 200, 700)
MEASURES = (
    "peak_force_n",
    "steady_force_n",
    "felt_force_n",
    "oscillation_rms_n",
    "swing_rms_n",
    "creep_n_s",
    "penetration_mm",
    "energy_generated_j",
    "master_dissipated_j",
    "slave_dissipated_j",
    "stable",
    "settled",
)


def run(
    delays_ms: tuple[int, ...] = DEFAULT_DELAYS_MS,
    jitter: float = 0.1,
    loss: float = 0.01,
    dofs: int = 1,
    seed: int = 1,
    master_limit: bool = True,
    slave_speed_m_s: float = SLAVE_SPEED_M_S,
    slave_port: bool = False,
    twist: bool = False,
) -> tuple[dict[str, Any], dict[tuple[int, bool], LoopResult]]:
    """(the JSON document, the traces per (delay, tdpa)). slave_port: the slave side is the
    decision service's own port (`LoopSpec.slave_port`), not the reference controller.
    twist: the press with a turn against a torsional stop (`LoopSpec.twist`; 3-DoF and the
    service's port, whatever `dofs` and `slave_port` say), the moment's measures too."""
    extra: dict[str, Any] = {}
    if twist:
        dofs, slave_port = 3, True
        extra["twist"] = Twist()
    if dofs == 3:
        extra |= {"dofs": 3, "target_m": (0.02, 0.0, 0.08), "wall": Wall(normal=(0.0, 0.0, 1.0))}
    doc: dict[str, Any] = {
        "settings": {
            "delays_ms": list(delays_ms),
            "jitter": jitter,
            "loss": loss,
            "dofs": dofs,
            "master_limit": master_limit,
            "slave_speed_m_s": slave_speed_m_s,
            "slave_port": slave_port,
            "twist": twist,
        },
    }
    results: dict[tuple[int, bool], LoopResult] = {}
    for delay in delays_ms:
        for on in (False, True):
            spec = LoopSpec(
                round_trip_s=delay / 1e3,
                jitter=jitter,
                loss=loss,
                tdpa=on,
                seed=seed,
                limit=master_limit,
                slave_speed_m_s=slave_speed_m_s,
                slave_port=slave_port,
                **extra,
            )
            res = simulate(spec)
            results[(delay, on)] = res
            parts = [("", contact_metrics(res))]
            if twist:
                parts.append(("moment_", twist_metrics(res)))
            put_measures(doc, delay, on, parts)
    return doc, results


SEED_FIGURES = (
    "stable",
    "settled",
    "swing_max_pct",
    "rms_max_pct",
    "felt_min_pct",
    "felt_max_pct",
    "generated_max_j",
)
"""Per delay and TDPA setting over seeds 1 … N (`seeds`): how many runs were stable and
settled; the largest swing and RMS (% of each run's steady force); the force felt as % of
the tool's (smallest, largest); the most energy generated."""


def seeds(
    count: int,
    delays_ms: tuple[int, ...] = DEFAULT_DELAYS_MS,
    jitter: float = 0.1,
    loss: float = 0.01,
    dofs: int = 1,
    master_limit: bool = True,
    slave_speed_m_s: float = SLAVE_SPEED_M_S,
    slave_port: bool = False,
    twist: bool = False,
) -> dict[str, Any]:
    """The same grid for seeds 1 … count (each its own jitter and losses), summed up as
    `passivity_<delay>_<on|off>_seeds_<figure>` keys (`SEED_FIGURES`): what one seed's
    table cannot say (a late step in one seed of six). With `twist`, the moment's too
    (`passivity_<delay>_<on|off>_moment_seeds_<figure>`)."""
    parts = ("", "moment_") if twist else ("",)
    runs: dict[tuple[int, str, str], list[dict[str, Any]]] = {}
    for seed in range(1, count + 1):
        doc, _ = run(
            delays_ms, jitter, loss, dofs, seed, master_limit, slave_speed_m_s, slave_port, twist
        )
        for delay in delays_ms:
            for on in ("off", "on"):
                for part in parts:
                    k = f"passivity_{delay}_{on}_{part}"
                    one = {m: doc[k + m] for m in MEASURES}
                    runs.setdefault((delay, on, part), []).append(one)

    out: dict[str, Any] = {}
    for (delay, on, part), ms in runs.items():
        k = f"passivity_{delay}_{on}_{part}seeds_"
        out |= {k + name: value for name, value in seed_figures(ms).items()}
    return out


def seed_figures(runs: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """`SEED_FIGURES` over the measures of several runs (`MEASURES` each). The percentages
    leave out a run with no steady force (diverged, or never in contact): null when no run
    had one, never an infinity (which is not JSON)."""

    def pct(name: str) -> list[float]:
        return [
            100.0 * float(m[name]) / float(m["steady_force_n"])
            for m in runs
            if float(m["steady_force_n"]) > 0.0
        ]

    def rounded(xs: list[float], pick: Callable[[list[float]], float]) -> float | None:
        return round(pick(xs), 3) if xs else None

    felt = pct("felt_force_n")
    return {
        "stable": sum(bool(m["stable"]) for m in runs),
        "settled": sum(bool(m["settled"]) for m in runs),
        "swing_max_pct": rounded(pct("swing_rms_n"), max),
        "rms_max_pct": rounded(pct("oscillation_rms_n"), max),
        "felt_min_pct": rounded(felt, min),
        "felt_max_pct": rounded(felt, max),
        "generated_max_j": max((float(m["energy_generated_j"]) for m in runs), default=None),
    }


def seeds_table(summary: dict[str, Any], delays_ms: tuple[int, ...], n: int, part: str = "") -> str:
    """`seeds`' figures over seeds 1 … n, one row per delay and TDPA setting (`part`:
    "moment_" for the twist's moment)."""
    head = (
        f"{'RTT ms':>7} {'TDPA':>4} {'stable':>7} {'settled':>7} {'swing max %':>11} "
        f"{'RMS max %':>9} {'felt % of tool':>14} {'gen. max J':>10}"
    )
    lines = [f"seeds 1 … {n}:", head, "-" * len(head)]
    for delay in delays_ms:
        for on in ("off", "on"):
            k = f"passivity_{delay}_{on}_{part}seeds_"
            lo, hi = summary[k + "felt_min_pct"], summary[k + "felt_max_pct"]
            felt = "–" if lo is None or hi is None else f"{lo:.0f}–{hi:.0f}"
            lines.append(
                f"{delay:>7} {on:>4} {summary[k + 'stable']:>3} / {n} "
                f"{summary[k + 'settled']:>3} / {n} {_num(summary[k + 'swing_max_pct'], 11, 1)} "
                f"{_num(summary[k + 'rms_max_pct'], 9, 1)} {felt:>14} "
                f"{_num(summary[k + 'generated_max_j'], 10, 4)}"
            )
    return "\n".join(lines)


def _num(x: float | None, width: int, digits: int) -> str:
    """A figure of the table; `–` where nothing was measured (null)."""
    return f"{'–':>{width}}" if x is None else f"{x:>{width}.{digits}f}"


def _yes_no(x: bool | None) -> str:
    return "–" if x is None else ("yes" if x else "NO")


def model_line(doc: dict[str, Any]) -> str:
    """What the table's figures are of: the simulated loop (services/control/passivity/
    loop.py) and its link, in one paragraph."""
    from services.control.passivity.dynamics import Device, Wall

    spec, wall, device = LoopSpec(), Wall(), Device(x=[0.0], v=[0.0])
    st = doc["settings"]
    slave = (
        "the decision's own slave port"
        if st.get("slave_port")
        else f"a kinematic slave chasing its target at ≤ {st.get('slave_speed_m_s')} m/s"
    )
    return (
        f"Model: a simulated {st.get('dofs', 1)}-DoF teleoperation loop at "
        f"{1 / spec.dt_s:.0f} Hz — a {wall.stiffness_n_m:g} N/m wall "
        f"({wall.damping_ns_m:g} N·s/m) {wall.offset_m * 100:g} cm away, a "
        f"{device.mass_kg:g} kg master device, an operator's hand aiming past the wall, "
        f"{slave}, display limit {spec.max_force_n:g} N; link: round trips "
        f"{st.get('delays_ms')} ms, jitter {st.get('jitter')}, loss {st.get('loss')} "
        "(docs/passivity.md). Forces in N along the wall's normal."
    )


def table(doc: dict[str, Any], part: str = "") -> str:
    """The results as a fixed-width table, one row per delay and TDPA setting (`part`:
    "moment_" for the twist's moment: N·m in place of N, mrad in place of mm)."""
    head = (
        f"{'RTT ms':>7} {'TDPA':>4} {'peak N':>8} {'steady N':>9} {'felt N':>7} {'osc RMS N':>10} "
        f"{'swing N':>8} {'creep N/s':>9} {'pen mm':>7} {'gen. J':>8} {'stable':>6} "
        f"{'settled':>7}"
    )
    lines = [head, "-" * len(head)]
    for delay in doc["settings"]["delays_ms"]:
        for on in ("off", "on"):
            k = f"passivity_{delay}_{on}_{part}"
            lines.append(
                f"{delay:>7} {on:>4} {_num(doc[k + 'peak_force_n'], 8, 1)} "
                f"{_num(doc[k + 'steady_force_n'], 9, 2)} "
                f"{_num(doc.get(k + 'felt_force_n'), 7, 2)} "
                f"{_num(doc[k + 'oscillation_rms_n'], 10, 2)} "
                f"{_num(doc.get(k + 'swing_rms_n'), 8, 2)} "
                f"{_num(doc.get(k + 'creep_n_s'), 9, 2)} "
                f"{_num(doc[k + 'penetration_mm'], 7, 1)} "
                f"{_num(doc[k + 'energy_generated_j'], 8, 3)} "
                f"{'yes' if doc[k + 'stable'] else 'NO':>6} "
                f"{_yes_no(doc.get(k + 'settled')):>7}"
            )
    return "\n".join(lines)


def loop_plot(res: LoopResult, delay: int, on: bool, path: Path) -> Path:
    """One run's PNG: the contact force, the force the operator felt and the force the
    hand intended (N, clipped at 50), and below, each port's energy reservoir (J: the
    energy that came in at the other port minus what this port gave out; with TDPA on
    neither stays below zero once the link's delay has passed)."""
    import numpy as np

    from services.tools.record.plots import BLACK, Series, panel, save_png, stack

    t = np.asarray(res.t, dtype=float)
    clip = lambda v: np.clip(np.asarray(v, dtype=float), 0.0, 50.0)  # noqa: E731
    forces = [
        Series.of("contact", t, clip(res.f_contact), BLACK),
        Series.of("felt", t, clip(res.f_display)),
        Series.of("intended (hand)", t, clip(res.f_hand)),
    ]
    # TDPA's reservoirs: what came in at the other port (as each side learns of it, here
    # without the link's delay) minus what this port gave out
    m_in, m_out = np.asarray(res.master_in, dtype=float), np.asarray(res.master_out, dtype=float)
    s_in, s_out = np.asarray(res.slave_in, dtype=float), np.asarray(res.slave_out, dtype=float)
    master_e, slave_e = s_in - m_out, m_in - s_out
    energies = [Series.of("master port", t, master_e), Series.of("slave port", t, slave_e)]
    title = f"{delay} ms round trip, TDPA {'on' if on else 'off'}"
    return save_png(
        path,
        stack(
            [
                panel(forces, f"forces, {title} (clipped at 50 N)", "time (s)", "force (N)"),
                panel(energies, f"energy reservoirs, {title}", "time (s)", "energy (J)"),
            ]
        ),
    )


def plots(results: dict[tuple[int, bool], LoopResult], out_dir: Path) -> list[Path]:
    """Per delay: contact force against time, TDPA off and on; per run: contact, felt and
    intended force and the ports' reservoirs (`loop_plot`); with the twist, the moment."""
    delays = sorted({d for d, _ in results})
    drawn = [
        off_on_plot(
            {on: (results[(delay, on)].t, results[(delay, on)].f_contact) for on in (False, True)},
            f"contact force, {delay} ms round trip (clipped at 50 N)",  # off reaches hundreds
            "time (s)",
            50.0,
            out_dir / f"passivity_{delay}ms.png",
        )
        for delay in delays
    ]
    drawn += [
        loop_plot(res, delay, on, out_dir / f"passivity_{delay}ms_{'on' if on else 'off'}.png")
        for (delay, on), res in sorted(results.items())
    ]
    if all(results[key].m_contact for key in results):
        drawn += [
            off_on_plot(
                {
                    on: (results[(delay, on)].t, results[(delay, on)].m_contact)
                    for on in (False, True)
                },
                f"contact moment, {delay} ms round trip (clipped at 3 N·m)",
                "time (s)",
                3.0,
                out_dir / f"passivity_{delay}ms_moment.png",
                "moment (N·m)",
            )
            for delay in delays
        ]
    return drawn


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="telerobot bench passivity", description=__doc__)
    p.add_argument(
        "--delays-ms",
        default=",".join(str(d) for d in DEFAULT_DELAYS_MS),
        help="round-trip delays, comma-separated (ms)",
    )
    p.add_argument("--jitter", type=float, default=0.1, help="fraction of the delay")
    p.add_argument("--loss", type=float, default=0.01, help="fraction of packets lost")
    p.add_argument("--dofs", type=int, default=1, choices=[1, 3])
    p.add_argument("--seed", type=int, default=1)
    p.add_argument(
        "--seeds",
        type=int,
        default=0,
        metavar="N",
        help="also run seeds 1 … N and sum them up per delay (stable and settled counts, "
        "the largest swing, the force felt, the energy generated); simulation only",
    )
    p.add_argument(
        "--no-master-limit",
        action="store_true",
        help="TDPA on without the master's force limiter (the damper alone)",
    )
    p.add_argument(
        "--slave-speed",
        type=float,
        default=None,
        metavar="M_S",
        help=f"the simulated slave's speed limit (default {SLAVE_SPEED_M_S:g} m/s, "
        "the arms' tool speed; 0: it jumps to each target in one tick)",
    )
    p.add_argument(
        "--slave-port",
        action="store_true",
        help="the simulated slave side is the decision service's own passivity port "
        "(default: the reference controller)",
    )
    p.add_argument(
        "--twist",
        action="store_true",
        help="the press with a turn against a torsional stop: a rotational port at each end "
        "(the moment's measures too; in the simulation 3-DoF and the services' ports; with "
        "--link the contact resists a turn about its normal and the master shows moments)",
    )
    p.add_argument(
        "--link",
        action="store_true",
        help="the real services over a real bad link (network namespaces; root)",
    )
    p.add_argument(
        "--tangential-gain",
        type=float,
        default=None,
        metavar="G",
        help="--link: the master's contact_tangential_gain, the part of the contact's force "
        "across its normal (its friction) shown, 0 … 1 (default 1: as measured; 0: the press "
        "alone)",
    )
    p.add_argument(
        "--model",
        choices=SHIPPED,
        default=None,
        help=f"--link: the simulated arm on the MuJoCo cell (default {DEFAULT_MODEL})",
    )
    p.add_argument(
        "--transport",
        choices=["tcp", "udp", "tls", "quic", "quic-mixed"],
        default="tcp",
        help="--link: Zenoh peers over TCP, or the operator as a client of a router over UDP, "
        "TLS, QUIC or QUIC with mixed reliability (the QUIC profile: deploy/operator-quic.toml)",
    )
    p.add_argument(
        "--approach-zone",
        type=float,
        default=None,
        metavar="M",
        help="--link: the decision's approach_zone_m (default 0.02: 2 cm/s within 2 cm of "
        "the table; 0: off)",
    )
    p.add_argument(
        "--rate-mbit",
        type=float,
        default=0.0,
        metavar="MBIT",
        help="--link: the link's bandwidth each way (0: unlimited; 0.5 is less than the "
        "streams need, so Zenoh's queues fill)",
    )
    p.add_argument(
        "--master-rate-hz",
        type=float,
        default=None,
        metavar="HZ",
        help="--link: the master station's loop rate (default 500, a haptic device's)",
    )
    p.add_argument(
        "--hold-s",
        type=float,
        default=None,
        metavar="S",
        help="--link: how long the operator holds the press (default 8; measured over its "
        "last 3 s)",
    )
    p.add_argument(
        "--yield",
        dest="yield_m_s_n",
        type=float,
        default=None,
        metavar="M_S_N",
        help="--link: the decision's passivity_yield_m_s_n (default: the decision's, 5e-5: "
        "the tool backs out to the force the hand feels while the round trip is at most "
        "500 ms; 0: off)",
    )
    p.add_argument(
        "--json", default=None, metavar="FILE", help="default artifacts/bench_passivity[_link].json"
    )
    p.add_argument("--plots", default="artifacts", metavar="DIR", help="'' for none")
    args = p.parse_args(argv)
    try:
        delays = tuple(int(x) for x in args.delays_ms.split(",") if x.strip())
    except ValueError:
        p.error("--delays-ms must be integers separated by commas")
    if not delays or any(not 0 <= d <= 10_000 for d in delays):
        p.error("--delays-ms must be within 0 … 10000")
    if not (0.0 <= args.jitter <= 1.0 and 0.0 <= args.loss < 1.0):
        p.error("--jitter must be within 0 … 1 and --loss within 0 … 1 (excluded)")
    if args.approach_zone is not None and not (args.link and 0.0 <= args.approach_zone <= 0.2):
        p.error("--approach-zone needs --link and a value within 0 … 0.2 m")
    if args.rate_mbit and not (args.link and 0.05 <= args.rate_mbit <= 10_000.0):
        p.error("--rate-mbit needs --link and a value within 0.05 … 10000")
    if args.master_rate_hz is not None and not (
        args.link and 10.0 <= args.master_rate_hz <= 1000.0
    ):
        p.error("--master-rate-hz needs --link and a value within 10 … 1000")
    if args.hold_s is not None and not (args.link and 1.0 <= args.hold_s <= 60.0):
        p.error("--hold-s needs --link and a value within 1 … 60")
    if args.yield_m_s_n is not None and not (args.link and 0.0 <= args.yield_m_s_n <= 1e-3):
        p.error("--yield needs --link and a value within 0 … 0.001 m/(N·s)")
    if args.slave_speed is not None and (args.link or not 0.0 <= args.slave_speed <= 10.0):
        p.error("--slave-speed is the simulation's (not --link) and within 0 … 10 m/s")
    if args.slave_port and (args.link or args.slave_speed == 0.0):
        p.error("--slave-port is the simulation's (not --link) and needs --slave-speed > 0")
    if args.tangential_gain is not None and not (args.link and 0.0 <= args.tangential_gain <= 1.0):
        p.error("--tangential-gain needs --link and a value within 0 … 1")
    if args.model is not None and not args.link:
        p.error("--model needs --link (the simulation is one degree of freedom, no arm)")
    if args.twist and args.slave_speed == 0.0:
        p.error("--twist needs --slave-speed > 0")
    if args.seeds and (args.link or not 1 <= args.seeds <= 100):
        p.error("--seeds is the simulation's (not --link) and within 1 … 100")
    summary: dict[str, Any] | None = None
    if args.link:
        from services.tools.tdpa import link_bench

        zone = link_bench.APPROACH_ZONE_M if args.approach_zone is None else args.approach_zone
        reason = link_bench.unavailable()
        if reason:
            print(f"telerobot bench passivity --link: {reason}", file=sys.stderr)
            return 2
        print(f"the real services over a bad link, {len(delays) * 2} runs:")
        doc, runs = link_bench.run_matrix(
            delays,
            args.jitter,
            args.loss,
            transport=args.transport,
            approach_zone_m=zone,
            rate_mbit=args.rate_mbit,
            master_rate_hz=(
                link_bench.MASTER_RATE_HZ if args.master_rate_hz is None else args.master_rate_hz
            ),
            hold_s=link_bench.HOLD_S if args.hold_s is None else args.hold_s,
            yield_m_s_n=(
                link_bench.YIELD_DEFAULT if args.yield_m_s_n is None else args.yield_m_s_n
            ),
            twist=args.twist,
            model=args.model or DEFAULT_MODEL,
            tangential_gain=1.0 if args.tangential_gain is None else args.tangential_gain,
        )
        path = Path(args.json or "artifacts/bench_passivity_link.json")
        drawn = link_bench.plots(runs, Path(args.plots)) if args.plots else []
    else:
        speed = SLAVE_SPEED_M_S if args.slave_speed is None else args.slave_speed
        limit = not args.no_master_limit
        doc, results = run(
            delays,
            args.jitter,
            args.loss,
            args.dofs,
            args.seed,
            limit,
            speed,
            args.slave_port,
            args.twist,
        )
        if args.seeds:
            summary = seeds(
                args.seeds,
                delays,
                args.jitter,
                args.loss,
                args.dofs,
                limit,
                speed,
                args.slave_port,
                args.twist,
            )
            doc |= summary
            doc["settings"]["seeds"] = args.seeds
        path = Path(args.json or "artifacts/bench_passivity.json")
        drawn = plots(results, Path(args.plots)) if args.plots else []
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=2) + "\n")
    print(link_bench.model_line(doc) if args.link else model_line(doc))
    print(table(doc))
    twisted = bool(doc["settings"].get("twist"))
    if twisted:
        print("\nthe moment (N·m in place of N, mrad past the stop in place of mm):")
        print(table(doc, "moment_"))
    if summary is not None:
        print("\n" + seeds_table(summary, delays, args.seeds))
        if twisted:
            print("\nthe moment, " + seeds_table(summary, delays, args.seeds, "moment_"))
    print(f"\nJSON: {path}" + (f"  plots: {', '.join(str(x) for x in drawn)}" if drawn else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
