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

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"
PREFIX = "/etc/telerobot/"
ROUTER_TCP = "tcp/0.0.0.0:7447"
ROUTER_TLS = "tls/0.0.0.0:7448"
LOCAL_TCP = "tcp/127.0.0.1:7447"


@dataclass(frozen=True, slots=True)
class Cell:
    """Paths of an installed cell: `root` stands for /etc/telerobot/."""

    root: Path
    tcp_port: int
    tls_port: int

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
) -> Cell:
    """Install deploy/ under `root` as a host would under /etc/telerobot/.

    ports: (tcp, tls) to listen on instead of 7447/7448, bound to `bind`; None keeps the
    shipped endpoints (inside a network namespace of our own).
    """
    (root / "zenoh").mkdir(parents=True, exist_ok=True)
    make_certs(root / "certs", *hosts)

    def rewrite(text: str) -> str:
        text = text.replace(PREFIX, f"{root}/")
        if ports is not None:
            tcp, tls = ports
            text = text.replace(ROUTER_TCP, f"tcp/{bind}:{tcp}")
            text = text.replace(ROUTER_TLS, f"tls/{bind}:{tls}")
            text = text.replace(LOCAL_TCP, f"tcp/127.0.0.1:{tcp}")
        return text

    copies = [
        *((p, root / "zenoh" / p.name) for p in (DEPLOY / "router").glob("*.json5")),
        *((p, root / "zenoh" / p.name) for p in (DEPLOY / "zenoh").glob("*.json5")),
        (DEPLOY / "robot.toml", root / "robot.toml"),
        (DEPLOY / "operator.toml", root / "operator.toml"),
    ]
    for src, dst in copies:
        dst.write_text(rewrite(src.read_text()))
    shutil.copy(DEPLOY / "router" / "users.txt", root / "zenoh" / "users.txt")
    tcp, tls = ports if ports is not None else (7447, 7448)
    return Cell(root, tcp, tls)
