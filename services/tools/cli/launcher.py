"""`telerobot up PROFILE`: run a set of services as child processes from a deploy/ profile.

A profile is a deployment TOML with an `[up]` table:

    [up]
    services = ["router", "arm", "force"]     # telerobot subcommands, started in order
    [up.args]                                  # extra arguments per service
    master = ["--device", "script"]
    [up.commands]                              # any other command, by name
    recorder = ["telerobot", "record", "-o", "session.mcap"]

Each child gets `--config PROFILE` (so it reads its own table and `[zenoh]`), its output is
prefixed with its name, a child that crashes is restarted with exponential backoff, and
Ctrl-C / SIGTERM stops all (SIGTERM, then SIGKILL after `stop_timeout_s`). Children stop
one by one in reverse start order. Children (`services.tools.cell.procs.Child`) are spawned,
never forked (ZENOH_NOTES.md pitfall 3).

What stops the whole launch (everything is stopped and `up` exits non-zero):
- before anything starts, the profile's router endpoint is taken (another Telerobot runs);
- a child exits with the configuration status (2): its configuration is wrong and a
  restart cannot mend it; the child and its last line (which names the key) are reported;
- a child exits within `startup_s` of its first start (it cannot start). Importing a
  service takes 3–13 s on a loaded 2-core machine, so the default is 30 s.

`--listen ENDPOINT` moves the profile's router to another endpoint (its services connect
there); `--ns NS` runs every service under a namespace and, when the router endpoint is
already taken, joins that router instead of starting one (several robots on one network);
`--model MODEL` runs the arm service with another arm model (puma560, fr3, ur5e, or the path
of an arm's TOML): every other service learns it from the arm's description; `--driver`
and `--robot-ip` its driver (`--driver libfranka --robot-ip HOST`: a Franka, or franky-sim,
docs/franka.md).
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from services.bus.config import load_deploy, section
from services.bus.errors import ConfigError
from services.bus.lifecycle import CONFIG_EXIT, Shutdown
from services.bus.router import DEFAULT_LISTEN, already_running, endpoint_taken, tcp_host_port
from services.tools.cell.procs import OUT_LOCK, Child, telerobot_argv

DEPLOY_DIR = Path(__file__).resolve().parents[3] / "deploy"


@dataclass(frozen=True, slots=True)
class UpConfig:
    """The `[up]` table of a profile."""

    services: tuple[str, ...] = ()
    args: dict[str, Any] = field(default_factory=dict)
    commands: dict[str, Any] = field(default_factory=dict)
    restart: bool = True
    backoff_s: float = 0.5
    backoff_max_s: float = 10.0
    startup_s: float = 30.0
    stop_timeout_s: float = 5.0

    def __post_init__(self) -> None:
        if not self.services and not self.commands:
            raise ConfigError("up.services", "no services and no commands to start")
        for name, extra in self.args.items():
            if not isinstance(extra, list) or not all(isinstance(a, str) for a in extra):
                raise ConfigError(f"up.args.{name}", "must be a list of strings")
        for name, cmd in self.commands.items():
            if not isinstance(cmd, list) or not cmd or not all(isinstance(a, str) for a in cmd):
                raise ConfigError(f"up.commands.{name}", "must be a non-empty list of strings")
        if self.backoff_s <= 0 or self.backoff_max_s < self.backoff_s:
            raise ConfigError("up.backoff_s", "need 0 < backoff_s ≤ backoff_max_s")
        if self.startup_s < 0:
            raise ConfigError("up.startup_s", "must be ≥ 0")
        if self.stop_timeout_s <= 0:
            raise ConfigError("up.stop_timeout_s", "must be > 0")


def resolve_profile(name: str) -> Path:
    """A profile path, or a name in deploy/ (`sim` → deploy/sim.toml)."""
    p = Path(name)
    if p.is_file():
        return p
    candidate = DEPLOY_DIR / f"{name}.toml"
    if candidate.is_file():
        return candidate
    known = sorted(x.stem for x in DEPLOY_DIR.glob("*.toml")) if DEPLOY_DIR.is_dir() else []
    raise ConfigError("profile", f"no profile {name!r} (known: {', '.join(known)})")


class UpChild(Child):
    """A child of `up`: its output prefixed on `out`, SIGTERM when `up` dies, and its
    supervision state."""

    def __init__(self, name: str, argv: list[str], out: IO[str]) -> None:
        super().__init__(name, argv, out=out, die_with_parent=True)
        self.next_start = 0.0
        #: exited and not to be restarted (restart = false): no longer supervised
        self.finished = False


@dataclass(frozen=True, slots=True)
class Overrides:
    """What `up --listen/--ns/--model` changes in a profile: the router's endpoint (its
    services connect there), a namespace for every service, the arm's model."""

    listen: str = ""
    ns: str = ""
    model: str = ""
    driver: str = ""
    robot_ip: str = ""

    def __post_init__(self) -> None:
        if self.listen and tcp_host_port(self.listen) is None:
            raise ConfigError("--listen", f"{self.listen!r} is not tcp/HOST:PORT")
        if self.ns and (self.ns.startswith("/") or self.ns.endswith("/") or "*" in self.ns):
            raise ConfigError("--ns", f"{self.ns!r}: no leading/trailing '/' or wildcards")


def child_argv(
    name: str, profile: Path, cfg: UpConfig, overrides: Overrides = Overrides()
) -> list[str]:
    if name in cfg.commands:
        return list(cfg.commands[name])
    extra: list[str] = []
    if overrides.listen:
        extra += ["--listen", overrides.listen] if name == "router" else []
        extra += [] if name == "router" else ["--connect", dialable(overrides.listen)]
    if overrides.ns and name != "router":
        extra += ["--ns", overrides.ns]
    if overrides.model and name == "arm":
        extra += ["--model", overrides.model]
    if overrides.driver and name == "arm":
        extra += ["--driver", overrides.driver]
    if overrides.robot_ip and name == "arm":
        extra += ["--robot-ip", overrides.robot_ip]
    return telerobot_argv(name, "--config", str(profile), *extra, *cfg.args.get(name, []))


def dialable(endpoint: str) -> str:
    """The endpoint a local service dials to reach a router listening on `endpoint`."""
    return endpoint.replace("0.0.0.0", "127.0.0.1").replace("[::]", "[::1]")


def router_endpoints(deploy: dict[str, Any], overrides: Overrides) -> list[str]:
    """The endpoints the profile's router will listen on (as `telerobot router` reads them)."""
    if overrides.listen:
        return [overrides.listen]
    table = deploy.get("router", {})
    if "listen" in table:
        return [str(e) for e in table["listen"]]
    return [] if table.get("zenoh_config") else [DEFAULT_LISTEN]


def taken_router_endpoints(deploy: dict[str, Any], overrides: Overrides) -> list[str]:
    """The profile router's endpoints that something already listens on."""
    return [e for e in router_endpoints(deploy, overrides) if endpoint_taken(e)]


def _say(out: IO[str], text: str) -> None:
    with OUT_LOCK:
        out.write(f"[up] {text}\n")
        out.flush()


def run(
    profile: Path,
    out: IO[str] = sys.stdout,
    stop: Shutdown | None = None,
    overrides: Overrides = Overrides(),
) -> int:
    """Start every child of `profile`, supervise them until stopped; the exit status."""
    deploy = load_deploy(profile)
    cfg = section(UpConfig, deploy.get("up"), "up")
    stop = stop or Shutdown()
    names = [*cfg.services, *cfg.commands]
    # The stop sequence takes up to stop_timeout_s per child: the last-resort thread dump
    # must not fire while it runs as designed (a SIGTERM from systemd or `timeout`).
    stop.grace_s = max(stop.grace_s, len(names) * (cfg.stop_timeout_s + 1.0) + 10.0)
    if "router" in cfg.services:
        taken = taken_router_endpoints(deploy, overrides)
        if taken and not overrides.ns:
            print(f"telerobot up: {already_running(taken)}", file=sys.stderr, flush=True)
            return 1
        if taken:
            names.remove("router")
            _say(
                out,
                f"a router already listens on {', '.join(taken)}: joining it under "
                f"namespace {overrides.ns!r} (no router of our own)",
            )
    children = [UpChild(n, child_argv(n, profile, cfg, overrides), out) for n in names]
    status = 0
    try:
        for c in children:
            c.start()
        while not stop.is_set():
            now = time.monotonic()
            for c in children:
                code = c.returncode
                if code is None or c.finished or c.next_start > now:
                    continue
                if c.next_start:  # a scheduled restart is due
                    c.next_start = 0.0
                    c.start()
                    continue
                if code == CONFIG_EXIT:
                    c.join_output()
                    c.say(
                        f"configuration error (exit {code}): {c.last_line or 'no message'}; "
                        "stopping everything"
                    )
                    status = 1
                    stop.set()
                    break
                if c.starts == 1 and now - c.started_at < cfg.startup_s and code != 0:
                    c.join_output()
                    c.say(f"could not start (exit {code}); stopping everything")
                    status = 1
                    stop.set()
                    break
                if not cfg.restart:
                    c.say(f"exited with {code}; not restarting")
                    c.finished = True
                    continue
                delay = min(cfg.backoff_s * 2 ** (c.starts - 1), cfg.backoff_max_s)
                c.say(f"exited with {code}; restarting in {delay:.1f} s")
                c.next_start = now + delay
            stop.wait(0.05)
    finally:
        # Stop in reverse start order, each before the next: the master and the decision
        # server leave the arm holding while the arm and the router are still there.
        for c in reversed(children):
            c.signal(signal.SIGTERM)
            if c.proc is not None and c.wait(cfg.stop_timeout_s) is None:
                c.say("did not stop in time; killing")
                c.kill()
            c.join_output()
            c.say(f"stopped (exit {c.returncode})")
    return status


def add_override_args(p: argparse.ArgumentParser) -> None:
    """`--listen` and `--ns`, shared by `telerobot up` and `telerobot demo`."""
    p.add_argument(
        "--listen",
        default="",
        metavar="ENDPOINT",
        help="the router's endpoint instead of the profile's, e.g. tcp/127.0.0.1:7450; "
        "every service connects there (run a second system beside a running one)",
    )
    p.add_argument(
        "--ns",
        default="",
        help="a namespace for every service (e.g. cell2); if the router endpoint is "
        "taken, join that router instead of starting one",
    )
    p.add_argument(
        "--model",
        default="",
        help="the arm model: puma560 (default), fr3, ur5e, or the path of an arm's TOML",
    )
    p.add_argument("--driver", default="", help="the arm's driver: sim (default), libfranka, …")
    p.add_argument("--robot-ip", default="", help="the Franka's address (--driver libfranka)")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="telerobot up",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "profile",
        nargs="?",
        default="sim",
        help="a profile file or a name in deploy/ (default: sim)",
    )
    add_override_args(p)
    args = p.parse_args(argv)
    from services.bus.sched import claim_cpu_share

    claim_cpu_share()  # the children share this session's autogroup (services.bus.sched)
    try:
        profile = resolve_profile(args.profile)
        overrides = Overrides(
            listen=args.listen,
            ns=args.ns,
            model=args.model,
            driver=args.driver,
            robot_ip=args.robot_ip,
        )
    except ConfigError as e:
        print(f"telerobot up: {e}", file=sys.stderr)
        return 2
    return run(profile, overrides=overrides)
