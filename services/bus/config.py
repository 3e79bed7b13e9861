"""Configuration from one place: the Zenoh flags every service shares, and the deployment TOML.

A deployment is one TOML file (see `deploy/*.toml`): a `[zenoh]` table for the node and
one table per service (`[arm]`, `[force]`, …). `section()` reads a table into the
service's frozen dataclass, so a misspelt key or a bad value fails at start-up with the key
named. Command-line flags override the file.
"""

from __future__ import annotations

import argparse
import difflib
import json
import tomllib
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import MISSING, dataclass, fields, is_dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeVar, get_args, get_origin, get_type_hints

from services.bus.bounds import short
from services.bus.errors import ConfigError

if TYPE_CHECKING:  # zenoh is imported where a session is configured: `--help` stays instant
    import zenoh

Mode = Literal["peer", "client", "router"]
MAX_LEASE_MS = 2000
#: the port `telerobot router` listens on unless told otherwise
ROUTER_PORT = 7447
#: the router on this machine, as a service or tool dials it when no endpoint is given
LOCAL_ROUTER = f"tcp/127.0.0.1:{ROUTER_PORT}"

T = TypeVar("T")


@dataclass(frozen=True, slots=True)
class NodeConfig:
    """How a node joins the Zenoh network.

    `lease_ms` ≤ 2000 so a frozen or cut-off peer is noticed within 2 s (PROTOCOL.md §5).
    Multicast scouting is off unless asked: labs share networks, and tests must not leak.
    `zenoh_config` is an optional JSON5 file (TLS, auth) applied first; the fields here
    override it.

    `shared_memory` is off by default (Zenoh's own default is on): with it, a payload of
    3 KB or more between local processes travels in a shared buffer from a pool that the
    publisher reuses once the reader's watchdog stops confirming it, and a subscriber
    starved of CPU then reads another message's bytes (reproduced: 359 of 1 232 20 kB
    payloads corrupt under starvation, 0 without; tests/bus/test_starvation.py). Our
    streams are small or compressed; loopback TCP carries them easily.

    `downsampling`: (key, max_hz) pairs, keys relative to `ns`: this node takes each key at
    most `max_hz` times a second; Zenoh drops the rest as they arrive (its ingress
    `downsampling`), before any Python runs. For a slow consumer of a fast stream (a plot
    of the 1 kHz force); never for commands or events, every one of which matters.

    `loopback`: the network interfaces that never leave this machine. The control class
    (commands, force, passivity energies: REAL_TIME, block on congestion, every one of them
    latest-wins) keeps blocking on links over these and drops on congestion on every other
    link this node sends on (`control_qos_rules`): a stalled TCP link to a remote operator
    would otherwise block the publisher's `put`, and with it the robot host's own readers
    (measured over a 700 ms link: 116–554 ms, 2–3 times a run; docs/deploy.md "A stalled
    link never blinds the robot host").
    Empty: no overwrite, the control class blocks everywhere.

    `timestamping`: the session stamps what it publishes (Zenoh's HLC), which a cached
    publisher (`Node.publisher(topic, cache=…)`, the arm's description) needs.
    """

    mode: Mode = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    ns: str = ""
    lease_ms: int = 1000
    multicast_scouting: bool = False
    zenoh_config: str = ""
    admin_space: bool = False
    shared_memory: bool = False
    downsampling: tuple[tuple[str, float], ...] = ()
    loopback: tuple[str, ...] = ("lo", "lo0")
    timestamping: bool = True

    def __post_init__(self) -> None:
        if self.mode not in ("peer", "client", "router"):
            raise ConfigError("zenoh.mode", f"must be peer, client or router, got {self.mode!r}")
        if not 100 <= self.lease_ms <= MAX_LEASE_MS:
            raise ConfigError("zenoh.lease_ms", f"must be within 100…{MAX_LEASE_MS} ms")
        for key, eps in (("zenoh.connect", self.connect), ("zenoh.listen", self.listen)):
            for ep in eps:
                if "/" not in ep:
                    raise ConfigError(key, f"endpoint {ep!r} is not PROTO/ADDRESS:PORT")
        if self.ns and (self.ns.startswith("/") or self.ns.endswith("/") or "*" in self.ns):
            raise ConfigError("zenoh.ns", f"{self.ns!r}: no leading/trailing '/' or wildcards")
        if self.zenoh_config and not Path(self.zenoh_config).is_file():
            raise ConfigError("zenoh.zenoh_config", f"no such file {self.zenoh_config!r}")
        for key, max_hz in self.downsampling:
            if not key or key.startswith("/") or key.endswith("/"):
                raise ConfigError("zenoh.downsampling", f"bad key {key!r}")
            if not 0.0 < max_hz < float("inf"):
                raise ConfigError("zenoh.downsampling", f"{key}: max_hz must be > 0, got {max_hz}")
        for name in self.loopback:
            if not name or len(name) > 15 or not name.isprintable() or "/" in name:
                raise ConfigError("zenoh.loopback", f"bad interface name {name[:20]!r}")

    def to_zenoh(self) -> zenoh.Config:
        """The zenoh.Config for this node."""
        import zenoh

        try:
            cfg = zenoh.Config.from_file(self.zenoh_config) if self.zenoh_config else zenoh.Config()
        except zenoh.ZError as e:
            raise ConfigError("zenoh.zenoh_config", str(e)) from None
        cfg.insert_json5("mode", json.dumps(self.mode))
        if self.connect:
            cfg.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        if self.listen:
            cfg.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        cfg.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        cfg.insert_json5("transport/link/tx/lease", str(self.lease_ms))
        cfg.insert_json5("transport/shared_memory/enabled", json.dumps(self.shared_memory))
        if self.ns:
            cfg.insert_json5("namespace", json.dumps(self.ns))
        if self.admin_space:
            cfg.insert_json5("adminspace/enabled", "true")
        if self.timestamping:
            cfg.insert_json5("timestamping/enabled", "true")
        if self.downsampling:
            # Zenoh matches these rules against the namespaced key: add the prefix here.
            prefix = f"{self.ns}/" if self.ns else ""
            rules = [{"key_expr": prefix + k, "freq": hz} for k, hz in self.downsampling]
            flow = {"flows": ["ingress"], "messages": ["put"], "rules": rules}
            cfg.insert_json5("downsampling", json.dumps([flow]))
        if self.loopback:
            # Ours first: a deployment's own rules (its zenoh_config) apply after them; a file
            # that carries ours already (deploy/router/*.json5, for zenohd) keeps its own.
            own = json.loads(cfg.get_json("qos/network") or "[]")
            ids = {r.get("id") for r in own}
            ours = [r for r in control_qos_rules(self.loopback) if r["id"] not in ids]
            cfg.insert_json5("qos/network", json.dumps(ours + own))
        return cfg


def control_qos_rules(loopback: Sequence[str]) -> list[dict[str, Any]]:
    """Zenoh `qos/network` rules: the control class drops on congestion when it leaves
    this machine, and blocks, as it is published, on links over `loopback` interfaces.

    Zenoh applies the rules in order to each message a link sends: the first turns every
    REAL_TIME blocking put into a dropping one, the second turns it back on a link whose
    every interface is a loopback one. The second cannot tell a put the first changed from
    one published REAL_TIME and dropping: on loopback that would block too (we publish
    none; REAL_TIME is the control class only, `streams._QOS`). deploy/router/*.json5 carry
    the same two rules.
    """
    base = {"messages": ["put"], "flows": ["egress"]}
    return [
        {
            "id": "control-drops-off-host",
            **base,
            "qos": {"priority": "real_time", "congestion_control": "block"},
            "overwrite": {"congestion_control": "drop"},
        },
        {
            "id": "control-blocks-on-loopback",
            **base,
            "interfaces": list(loopback),
            "qos": {"priority": "real_time", "congestion_control": "drop"},
            "overwrite": {"congestion_control": "block"},
        },
    ]


def add_node_args(parser: argparse.ArgumentParser) -> None:
    """The Zenoh flags, parsed in one place for every service and tool."""
    g = parser.add_argument_group("zenoh")
    g.add_argument(
        "--connect",
        "-e",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help="endpoint to connect to, e.g. tcp/192.168.1.10:7447 (repeatable)",
    )
    g.add_argument(
        "--listen",
        "-l",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help="endpoint to listen on, e.g. tcp/0.0.0.0:7448 (repeatable)",
    )
    g.add_argument(
        "--mode",
        "-m",
        choices=["peer", "client", "router"],
        default=None,
        help="Zenoh session mode (tools default to a peer that connects to the local router)",
    )
    g.add_argument("--ns", default=None, help="namespace prefix, e.g. cell2")
    g.add_argument(
        "--config",
        "-c",
        default=None,
        metavar="FILE",
        help="deployment TOML (deploy/*.toml): [zenoh] and per-service tables",
    )
    g.add_argument(
        "--zenoh-config",
        default=None,
        metavar="FILE",
        help="a Zenoh JSON5 config (TLS, auth) applied before the flags",
    )
    g.add_argument("--lease-ms", type=int, default=None, help="link lease (≤ 2000 ms)")
    g.add_argument(
        "--multicast",
        action="store_true",
        default=None,
        help="enable multicast scouting (off by default)",
    )


TABLES = frozenset(
    {"zenoh", "router", "up", "arm", "force", "decision", "vision", "console", "master", "ros2"}
    | {"workcell", "record", "physics", "scene"}
)
"""The tables a deployment file may have: one per service, `[zenoh]` for every session,
`[router]` and `[up]` for the launcher. Any other is refused: a misspelt `[decison]` would
otherwise drop its safety settings without a word."""


def load_deploy(path: str | Path | None) -> dict[str, Any]:
    """The deployment TOML as a dict (empty when no file). A table not in `TABLES`, or a
    top-level key outside a table, is a ConfigError naming it and the known ones."""
    if not path:
        return {}
    p = Path(path)
    try:
        with p.open("rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError("--config", f"no such file {str(p)!r}") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError("--config", f"{p}: {e}") from None
    for name, value in data.items():
        if not isinstance(value, dict):
            raise ConfigError(
                short(name, 40), f"{p}: a key outside any table; put it in its [service]"
            )
        if name not in TABLES:
            near = difflib.get_close_matches(name, sorted(TABLES), n=1)
            hint = f" (did you mean [{near[0]}]?)" if near else ""
            raise ConfigError(
                short(name, 40),
                f"{p}: unknown table [{short(name, 40)}]{hint}; known: "
                + ", ".join(f"[{t}]" for t in sorted(TABLES)),
            )
    return data


def node_config(
    args: argparse.Namespace, deploy: Mapping[str, Any] | None = None, **defaults: Any
) -> NodeConfig:
    """NodeConfig from `defaults` < the deployment's [zenoh] table < command-line flags."""
    deploy = deploy if deploy is not None else load_deploy(getattr(args, "config", None))
    base = section(NodeConfig, {**defaults, **dict(deploy.get("zenoh", {}))}, "zenoh")
    flags: dict[str, Any] = {}
    for attr, key in (("connect", "connect"), ("listen", "listen")):
        v = getattr(args, attr, None)
        if v:
            flags[key] = tuple(v)
    for attr, key in (
        ("mode", "mode"),
        ("ns", "ns"),
        ("zenoh_config", "zenoh_config"),
        ("lease_ms", "lease_ms"),
        ("multicast", "multicast_scouting"),
    ):
        v = getattr(args, attr, None)
        if v is not None:
            flags[key] = v
    return replace(base, **flags) if flags else base


def section(cls: type[T], data: Mapping[str, Any] | None, name: str) -> T:
    """Build the frozen dataclass `cls` from a TOML table, naming any bad key as `name.key`.

    Unknown keys are refused; values are checked against the field annotations (int, float,
    bool, str, Literal, tuples, nested dataclasses); `cls.__post_init__` checks ranges.
    """
    if not is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    data = dict(data or {})
    hints = get_type_hints(cls)
    known = {f.name for f in fields(cls)}
    for key in data:
        if key not in known:
            raise ConfigError(f"{name}.{key}", f"unknown key (known: {', '.join(sorted(known))})")
    values = {k: _coerce(f"{name}.{k}", hints[k], v) for k, v in data.items()}
    missing = [
        f.name
        for f in fields(cls)
        if f.name not in values and f.default is MISSING and f.default_factory is MISSING
    ]
    if missing:
        raise ConfigError(f"{name}.{missing[0]}", "required")
    try:
        return cls(**values)
    except ConfigError:
        raise
    except (TypeError, ValueError) as e:
        raise ConfigError(name, str(e)) from None


def _coerce(key: str, tp: Any, v: Any) -> Any:
    origin = get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = get_args(tp)
        if v is None and type(None) in args:
            return None
        last: ConfigError | None = None
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(key, a, v)
            except ConfigError as e:
                last = e
        raise last or ConfigError(key, f"bad value {v!r}")
    if origin is Literal:
        if v not in get_args(tp):
            raise ConfigError(key, f"must be one of {list(get_args(tp))}, got {v!r}")
        return v
    if tp is bool:
        if not isinstance(v, bool):
            raise ConfigError(key, f"expected true/false, got {v!r}")
        return v
    if tp is int:
        if isinstance(v, bool) or not isinstance(v, int):
            raise ConfigError(key, f"expected an integer, got {v!r}")
        return v
    if tp is float:
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise ConfigError(key, f"expected a number, got {v!r}")
        if v != v or v in (float("inf"), float("-inf")):
            raise ConfigError(key, "must be finite")
        return float(v)
    if tp is str:
        if not isinstance(v, str):
            raise ConfigError(key, f"expected a string, got {v!r}")
        return v
    if origin is tuple:
        if not isinstance(v, list | tuple):
            raise ConfigError(key, f"expected a list, got {v!r}")
        args = get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(f"{key}[{i}]", args[0], x) for i, x in enumerate(v))
        if len(args) != len(v):
            raise ConfigError(key, f"expected {len(args)} items, got {len(v)}")
        return tuple(
            _coerce(f"{key}[{i}]", a, x) for i, (a, x) in enumerate(zip(args, v, strict=True))
        )
    if is_dataclass(tp) and isinstance(tp, type):
        if not isinstance(v, Mapping):
            raise ConfigError(key, f"expected a table, got {v!r}")
        return section(tp, v, key)
    if origin is dict:
        # A free-form table (e.g. [up.commands]): TOML keys are strings; values by type.
        if not isinstance(v, Mapping):
            raise ConfigError(key, f"expected a table, got {v!r}")
        value_tp = get_args(tp)[1] if get_args(tp) else typing.Any
        return {str(k): _coerce(f"{key}.{k}", value_tp, x) for k, x in v.items()}
    if tp is typing.Any:
        return v
    raise ConfigError(key, f"unsupported type {tp!r}")


def service_config(
    cls: type[T], args: argparse.Namespace, name: str, overrides: Mapping[str, Any] | None = None
) -> T:
    """The `[name]` table of the deployment file named by `--config`, plus `overrides`."""
    deploy = load_deploy(getattr(args, "config", None))
    return section(cls, service_table(deploy, name, overrides), name)


def service_table(
    deploy: Mapping[str, Any], name: str, overrides: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """The deployment's `[name]` table with the command-line `overrides` that were given
    (None means the flag was not given and the file's value stands)."""
    table = dict(deploy.get(name, {}))
    table.update({k: v for k, v in (overrides or {}).items() if v is not None})
    return table


def endpoints(value: Sequence[str] | str | None) -> tuple[str, ...]:
    """Normalise one endpoint or a list of them to a tuple."""
    if value is None:
        return ()
    return (value,) if isinstance(value, str) else tuple(value)
