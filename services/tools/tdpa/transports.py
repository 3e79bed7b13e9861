"""The Zenoh transports the emulated link carries: each one's endpoint and, for the secure
ones (TLS, QUIC), the cell's certificates and the two Zenoh files that name them.

Both link benches dial through these: `telerobot bench link` (services.tools.bench.link)
and `telerobot bench passivity --link` (services.tools.tdpa.link_bench).
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

TRANSPORTS = ("tcp", "tls", "udp", "quic", "quic-mixed")
MAKE_CERTS = Path(__file__).resolve().parents[3] / "deploy" / "certs" / "make-certs.sh"


def endpoint(transport: str, host: str, port: int) -> str:
    """The Zenoh endpoint of `transport` (one of TRANSPORTS) on host:port; listener and
    connector must agree, `?mixed_rel=1` included."""
    if transport not in TRANSPORTS:
        raise ValueError(f"transport {transport!r} is not one of {TRANSPORTS}")
    if transport == "quic-mixed":
        return f"quic/{host}:{port}?mixed_rel=1"
    return f"{transport}/{host}:{port}"


def secure(transport: str) -> bool:
    return transport in ("tls", "quic", "quic-mixed")


def write_tls_configs(certs: Path, host: str) -> tuple[Path, Path]:
    """A CA and the router's certificate for `host` (deploy/certs/make-certs.sh, as a cell
    makes them), and the two Zenoh files: (router's, client's). TLS and QUIC read the same
    `transport/link/tls` block."""
    done = subprocess.run(
        ["bash", str(MAKE_CERTS), "-o", str(certs), host],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    if done.returncode != 0:
        raise RuntimeError(f"make-certs.sh failed: {done.stderr.strip()[-400:]}")
    router = certs / "router.json5"
    client = certs / "client.json5"
    tls_router = {
        "listen_certificate": str(certs / "router.pem"),
        "listen_private_key": str(certs / "router.key"),
        "root_ca_certificate": str(certs / "ca.pem"),
    }
    tls_client = {"root_ca_certificate": str(certs / "ca.pem"), "verify_name_on_connect": True}
    router.write_text(json.dumps({"transport": {"link": {"tls": tls_router}}}))
    client.write_text(json.dumps({"transport": {"link": {"tls": tls_client}}}))
    return router, client
