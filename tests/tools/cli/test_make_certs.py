"""deploy/certs/make-certs.sh as the README writes it (issue 23 item 12): options anywhere,
a client certificate for `-c NAME` after the hosts, and a loud failure (exit 2, nothing
written) for anything it cannot honour. Runs openssl in a temporary directory."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from tests.bus.test_router import REPO

SCRIPT = REPO / "deploy" / "certs" / "make-certs.sh"

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl")


def make_certs(cwd: Path, *argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["bash", str(SCRIPT), *argv], cwd=cwd, capture_output=True, text=True, timeout=60
    )


def x509(path: Path, *what: str) -> str:
    done = subprocess.run(
        ["openssl", "x509", "-in", str(path), "-noout", *what],
        capture_output=True,
        text=True,
        timeout=30,
        check=True,
    )
    return done.stdout


def san_of(path: Path) -> list[str]:
    text = x509(path, "-ext", "subjectAltName").splitlines()[-1]
    return [s.strip() for s in text.split(",")]


def test_the_readme_form_makes_a_client_certificate(tmp_path: Path) -> None:
    done = make_certs(tmp_path, "robot.lab.example", "10.0.0.5", "-c", "operator1")
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "ca.key",
        "ca.pem",
        "operator1.key",
        "operator1.pem",
        "router.key",
        "router.pem",
    ]
    assert san_of(tmp_path / "router.pem") == ["DNS:robot.lab.example", "IP Address:10.0.0.5"]
    # the CN is the role the router's ACL and users.txt know; the station is the OU
    assert x509(tmp_path / "operator1.pem", "-subject").strip() == (
        "subject=OU = operator1, CN = operator"
    )
    assert "the ACL's operator role" in done.stdout
    usage = x509(tmp_path / "operator1.pem", "-ext", "extendedKeyUsage")
    assert "TLS Web Client Authentication" in usage
    subprocess.run(
        ["openssl", "verify", "-CAfile", "ca.pem", "operator1.pem", "router.pem"],
        cwd=tmp_path,
        check=True,
        capture_output=True,
        timeout=30,
    )


def test_options_between_and_after_hosts_and_joined_values(tmp_path: Path) -> None:
    out = tmp_path / "cell"
    done = make_certs(tmp_path, "robot.a", "-c", "s1", "192.0.2.1", "-o", str(out), "-cs2")
    assert done.returncode == 0, done.stderr
    assert san_of(out / "router.pem") == ["DNS:robot.a", "IP Address:192.0.2.1"]
    assert {p.name for p in out.glob("*.pem")} == {"ca.pem", "router.pem", "s1.pem", "s2.pem"}
    assert list(tmp_path.glob("*.pem")) == []


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["robot.a", "-x"], "unknown option '-x'"),
        (["robot.a", "-c"], "-c needs a value"),
        (["robot.a", "-c", "-o", "dir"], "-c needs a value"),
        (["-c", "operator1"], "give at least one ROBOT_HOST"),
        (["robot.a", "-c", "a b"], "bad client name 'a b'"),
        (["robot.a", "-c", "router"], "'router' is reserved"),
        (["robot.a", "-d", "ten"], "-d takes a number of days"),
        (["robot a"], "'robot a' is not a host name"),
        (["--", "-c"], "'-c' is not a host name"),
    ],
)
def test_what_it_cannot_honour_fails_loudly_and_writes_nothing(
    tmp_path: Path, argv: list[str], message: str
) -> None:
    done = make_certs(tmp_path, *argv)
    assert done.returncode == 2 and f"make-certs.sh: {message}" in done.stderr
    assert "usage: make-certs.sh" in done.stderr
    assert list(tmp_path.iterdir()) == []


def test_help_exits_0(tmp_path: Path) -> None:
    done = make_certs(tmp_path, "-h")
    assert done.returncode == 0 and "Options may come anywhere" in done.stderr
    assert list(tmp_path.iterdir()) == []
