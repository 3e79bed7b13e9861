"""The transports across the emulated link (issue 41): each one's endpoint, and the TLS files
for the secure ones, a chain make-certs.sh made for the host."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from services.tools.tdpa import transports


def test_each_transport_has_its_endpoint_and_quic_mixed_its_metadata() -> None:
    got = {t: transports.endpoint(t, "10.203.0.1", 7449) for t in transports.TRANSPORTS}
    assert got == {
        "tcp": "tcp/10.203.0.1:7449",
        "tls": "tls/10.203.0.1:7449",
        "udp": "udp/10.203.0.1:7449",
        "quic": "quic/10.203.0.1:7449",
        "quic-mixed": "quic/10.203.0.1:7449?mixed_rel=1",
    }
    assert [t for t in transports.TRANSPORTS if transports.secure(t)] == [
        "tls",
        "quic",
        "quic-mixed",
    ]
    with pytest.raises(ValueError, match="sctp"):
        transports.endpoint("sctp", "h", 1)


def test_the_tls_files_name_a_chain_make_certs_made_for_the_host(tmp_path: Path) -> None:
    router, client = transports.write_tls_configs(tmp_path, "10.203.0.1")
    r = json.loads(router.read_text())["transport"]["link"]["tls"]
    c = json.loads(client.read_text())["transport"]["link"]["tls"]
    for path in (r["listen_certificate"], r["listen_private_key"], c["root_ca_certificate"]):
        assert Path(path).is_file()
    assert c["verify_name_on_connect"] is True
    import subprocess

    san = subprocess.run(
        ["openssl", "x509", "-in", r["listen_certificate"], "-noout", "-ext", "subjectAltName"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert "IP Address:10.203.0.1" in san
