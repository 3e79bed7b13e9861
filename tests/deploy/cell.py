"""A cell installed into a temporary directory from the real deploy/ files.

Every file is copied as it ships; the only rewrites are the install prefix
(`/etc/telerobot/` → the temporary directory) and, where a test asks, the listen ports (so
tests do not need the well-known 7447/7448 on the test machine). Certificates come from
deploy/certs/make-certs.sh itself.
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from services.tools.cell.ports import free_udp_port

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"
PREFIX = "/etc/telerobot/"
ROUTER_TCP = "tcp/0.0.0.0:7447"
ROUTER_TLS = "tls/0.0.0.0:7448"
ROUTER_QUIC = "quic/0.0.0.0:7449"
LOCAL_TCP = "tcp/127.0.0.1:7447"


@dataclass(frozen=True, slots=True)
class Cell:
    """Paths of an installed cell: `root` stands for /etc/telerobot/."""

    root: Path
    tcp_port: int
    tls_port: int
    quic_port: int = 7449

    @property
    def zenoh_dir(self) -> Path:
        return self.root / "zenoh"

    @property
    def certs(self) -> Path:
        return self.root / "certs"

    def profile(self, name: str) -> Path:
        return self.root / f"{name}.toml"

    def client_file(self, name: str) -> Path:
        return self.zenoh_dir / f"{name}.json5"

    def variant(self, name: str, edit: Callable[[str], str], new_name: str) -> Path:
        """A copy of an installed file with one edit (a wrong password, a missing CA…)."""
        src = self.zenoh_dir / name
        dst = self.zenoh_dir / new_name
        text = src.read_text()
        changed = edit(text)
        assert changed != text, f"the edit changed nothing in {name}"
        dst.write_text(changed)
        return dst


def make_certs(out: Path, *hosts: str, clients: tuple[str, ...] = ()) -> str:
    """Run deploy/certs/make-certs.sh; its standard output."""
    argv = ["bash", str(DEPLOY / "certs" / "make-certs.sh"), "-o", str(out)]
    for c in clients:
        argv += ["-c", c]
    done = subprocess.run([*argv, *hosts], capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    return done.stdout


def install(
    root: Path,
    hosts: tuple[str, ...] = ("localhost", "127.0.0.1"),
    ports: tuple[int, int] | None = None,
    bind: str = "127.0.0.1",
    clients: tuple[str, ...] = (),
    prefix: str | None = None,
) -> Cell:
    """Install deploy/ under `root` as a host would under /etc/telerobot/.

    ports: (tcp, tls) to listen on instead of 7447/7448, bound to `bind` (QUIC then listens
    on a free UDP port of its own instead of 7449); None keeps the shipped endpoints (inside
    a network namespace of our own). clients: make-certs.sh's `-c` names (default: its own).
    prefix: the path the files name for /etc/telerobot/ (default `root`; "/etc/telerobot/"
    for a folder mounted there in containers).
    """
    (root / "zenoh").mkdir(parents=True, exist_ok=True)
    make_certs(root / "certs", *hosts, clients=clients)
    quic = free_udp_port() if ports is not None else 7449

    def rewrite(text: str) -> str:
        text = text.replace(PREFIX, prefix or f"{root}/")
        if ports is not None:
            tcp, tls = ports
            text = text.replace(ROUTER_TCP, f"tcp/{bind}:{tcp}")
            text = text.replace(ROUTER_TLS, f"tls/{bind}:{tls}")
            text = text.replace(ROUTER_QUIC, f"quic/{bind}:{quic}")
            text = text.replace(LOCAL_TCP, f"tcp/127.0.0.1:{tcp}")
        return text

    copies = [
        *((p, root / "zenoh" / p.name) for p in (DEPLOY / "router").glob("*.json5")),
        *((p, root / "zenoh" / p.name) for p in (DEPLOY / "zenoh").glob("*.json5")),
        (DEPLOY / "robot.toml", root / "robot.toml"),
        *((p, root / p.name) for p in DEPLOY.glob("operator*.toml")),
    ]
    for src, dst in copies:
        dst.write_text(rewrite(src.read_text()))
    shutil.copy(DEPLOY / "router" / "users.txt", root / "zenoh" / "users.txt")
    tcp, tls = ports if ports is not None else (7447, 7448)
    return Cell(root, tcp, tls, quic)


def edit(path: Path, *pairs: tuple[str, str]) -> None:
    """Replace each `old` (which must be there) by `new` in the file."""
    text = path.read_text()
    for old, new in pairs:
        assert old in text, f"{path.name} has no {old!r}"
        text = text.replace(old, new)
    path.write_text(text)


def without_hardware(cell: Cell, console_port: int, master: str = 'device = "scripted"') -> None:
    """The edits a lab makes to try an installed cell without its hardware: the simulated
    arm, sensor and cameras on the robot host; on the station, `master` for the SpaceMouse
    line, the console on `console_port`, the router dialled at localhost."""
    edit(
        cell.profile("robot"),
        ('driver = "serial"', 'driver = "sim"'),
        ('sensor = "serial"', 'sensor = "sim"'),
        # SCHED_FIFO (with a spinning sampler) on a shared test machine is not ours to take
        ('priority = "highest"', 'priority = "normal"'),
        ('camera = "opencv"', 'camera = "sim"'),
        ("devices = [0, 2]\n", ""),
    )
    edit(
        cell.profile("operator"),
        ('device = "spacemouse"', master),
        ("port = 8080", f"port = {console_port}"),
        ("tls/robot.lab.example:7448", f"tls/localhost:{cell.tls_port}"),
    )
