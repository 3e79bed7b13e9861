"""A Docker engine, the images and `docker compose` for tests/deploy/test_compose.py.

What a host needs is installed by `make compose-deps` (docker.io, docker-compose,
debootstrap, when missing); here the engine is started where it is installed but not
running (and stopped again afterwards), the base image is had however this host can have
it, and our image is built from the repository as deploy/Dockerfile says.

The base, in order: `TELEROBOT_BASE` if set; the official `python:3.11-slim-bookworm` when
it is on this host (the test never pulls: `docker pull` it first); else one made from
Debian's packages by deploy/make-base-image.sh (no image registry needed), trusting the CAs
this host trusts besides Debian's (/usr/local/share/ca-certificates: a TLS-inspecting
proxy's), so that pip inside the build reaches PyPI as the host's pip does.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import subprocess
import tempfile
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from tests.deploy.cell import DEPLOY, REPO

OFFICIAL_BASE = "python:3.11-slim-bookworm"
LOCAL_BASE = "telerobot-base:3.11-bookworm"
IMAGE = "telerobot:0.1"
LOCAL_CAS = Path("/usr/local/share/ca-certificates")
ENGINE_START_S = 60.0
BUILD_S = 1800.0


class DockerUnavailable(Exception):
    """No Docker engine or compose can be had here; the message says what is missing."""


def run(
    argv: Sequence[str],
    timeout_s: float = 120.0,
    check: bool = True,
    env: dict[str, str] | None = None,
    input_text: str | None = None,
) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(
        list(argv),
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
        env=None if env is None else {**os.environ, **env},
        input=input_text,
    )
    if check and done.returncode != 0:
        tail = "\n".join((done.stdout + done.stderr).strip().splitlines()[-30:])
        raise RuntimeError(f"{' '.join(argv)} exited {done.returncode}:\n{tail}")
    return done


def answers() -> bool:
    """Whether a Docker engine answers the client."""
    if shutil.which("docker") is None:
        return False
    return run(["docker", "info"], timeout_s=30, check=False).returncode == 0


@contextlib.contextmanager
def engine(log_dir: Path) -> Iterator[str]:
    """A running Docker engine; yields how it was had ("running" or "started").

    Started here (and stopped on exit) only where none answers: `dockerd
    --storage-driver=vfs`, the one driver that works on every kernel and file system
    (overlay2 needs what a container-in-VM host may lack), logging to log_dir/dockerd.log.
    """
    if shutil.which("docker") is None:
        raise DockerUnavailable("no docker client (apt-get install docker.io; make compose-deps)")
    if answers():
        yield "running"
        return
    dockerd = shutil.which("dockerd")
    if dockerd is None:
        raise DockerUnavailable("no dockerd (apt-get install docker.io; make compose-deps)")
    args = os.environ.get("TELEROBOT_DOCKERD_ARGS", "--storage-driver=vfs").split()
    log = (log_dir / "dockerd.log").open("w")
    proc = subprocess.Popen([dockerd, *args], stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + ENGINE_START_S
        while not answers():
            if proc.poll() is not None or time.monotonic() > deadline:
                tail = (log_dir / "dockerd.log").read_text().splitlines()[-15:]
                raise DockerUnavailable("dockerd did not start:\n" + "\n".join(tail))
            time.sleep(0.5)
        yield "started"
    finally:
        proc.terminate()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)
        log.close()


def has_image(name: str) -> bool:
    return run(["docker", "image", "inspect", name], timeout_s=30, check=False).returncode == 0


def base_script(image: str) -> str:
    """The hash of the make-base-image.sh that made `image` (its label), or ""."""
    fmt = '{{index .Config.Labels "org.telerobot.base-script"}}'
    done = run(["docker", "image", "inspect", "-f", fmt, image], timeout_s=30, check=False)
    return done.stdout.strip() if done.returncode == 0 else ""


def local_cas() -> list[Path]:
    """The CA certificates this host trusts besides its distribution's."""
    if not LOCAL_CAS.is_dir():
        return []
    return sorted(p for p in LOCAL_CAS.rglob("*.crt") if p.is_file())


def base_image(notes: list[str]) -> str:
    """The BASE build argument to use here; `notes` gets a line saying which and why."""
    chosen = os.environ.get("TELEROBOT_BASE")
    if chosen:
        notes.append(f"base {chosen} (TELEROBOT_BASE)")
        return chosen
    if has_image(OFFICIAL_BASE):
        notes.append(f"base {OFFICIAL_BASE} (already here)")
        return OFFICIAL_BASE
    # Never pulled: a test talks to no registry or host but loopback (the image build's pip
    # and the Debian base's debootstrap are installs, as make's are). `docker pull` it
    # beforehand to build on the official image.
    why = "not on this host (the test never pulls)"
    script = DEPLOY / "make-base-image.sh"
    made_by = hashlib.sha256(script.read_bytes()).hexdigest()
    if has_image(LOCAL_BASE) and base_script(LOCAL_BASE) == made_by:
        notes.append(f"base {LOCAL_BASE} (made earlier; {OFFICIAL_BASE} {why})")
        return LOCAL_BASE
    argv = ["bash", str(script), "-t", LOCAL_BASE]
    for ca in local_cas():
        argv += ["--ca", str(ca)]
    made = run(argv, timeout_s=600)
    notes.append(f"base {LOCAL_BASE} ({OFFICIAL_BASE} {why}); {made.stdout}")
    return LOCAL_BASE


def build_context(dest: Path) -> Path:
    """The build context deploy/Dockerfile.dockerignore describes, as a folder of its own.

    The classic builder (the one every client has; BuildKit needs buildx with newer clients
    and failed on 20.10's vfs driver here) reads only a .dockerignore at the context's root,
    so the `!` entries of Dockerfile.dockerignore are copied instead, less its exclusions.
    """
    lines = (DEPLOY / "Dockerfile.dockerignore").read_text().splitlines()
    entries = [ln.strip() for ln in lines if ln.strip() and not ln.startswith("#")]
    assert entries[0] == "*", "Dockerfile.dockerignore no longer starts by excluding all"
    dest.mkdir(parents=True)
    for entry in entries[1:]:
        if not entry.startswith("!"):
            continue
        name = entry[1:].rstrip("/")
        src = REPO / name
        if src.is_dir():
            shutil.copytree(src, dest / name)
        else:
            shutil.copy2(src, dest / name)
    for entry in entries[1:]:
        if entry.startswith("!"):
            continue
        for hit in list(dest.glob(entry)):
            shutil.rmtree(hit) if hit.is_dir() else hit.unlink()
    return dest


def build_image(base: str, work: Path) -> float:
    """Build IMAGE from deploy/Dockerfile on `base`; the seconds it took."""
    ctx = build_context(work / "context")
    t0 = time.monotonic()
    run(
        [
            "docker",
            "build",
            "-f",
            str(ctx / "deploy" / "Dockerfile"),
            "--build-arg",
            f"BASE={base}",
            "-t",
            IMAGE,
            str(ctx),
        ],
        timeout_s=BUILD_S,
        env={"DOCKER_BUILDKIT": "0"},
    )
    return time.monotonic() - t0


def build_zenohd_image(zenohd: Path, base: str, tag: str) -> None:
    """deploy/zenohd.Dockerfile around a zenohd binary built here (`make zenohd`)."""
    with tempfile.TemporaryDirectory() as ctx:
        shutil.copy2(zenohd, Path(ctx) / "zenohd")
        run(
            [
                "docker",
                "build",
                "-f",
                str(DEPLOY / "zenohd.Dockerfile"),
                "--build-arg",
                f"BASE={base}",
                "-t",
                tag,
                ctx,
            ],
            timeout_s=300,
            env={"DOCKER_BUILDKIT": "0"},
        )


def compose_command() -> list[str]:
    """Compose v2: `docker compose` (the plugin), or a `docker-compose` of v2.

    Compose v1 (Debian bookworm's docker-compose 1.29) does not read the Compose
    specification's top-level `name:` that keeps the two stacks apart on one host;
    `make compose-deps` builds v2 where only v1 can be had."""
    if run(["docker", "compose", "version"], timeout_s=30, check=False).returncode == 0:
        return ["docker", "compose"]
    if shutil.which("docker-compose"):
        out = run(["docker-compose", "version", "--short"], timeout_s=30, check=False)
        if out.returncode == 0 and out.stdout.strip().lstrip("v").startswith("2."):
            return ["docker-compose"]
        raise DockerUnavailable(
            f"docker-compose {out.stdout.strip()} is Compose v1, which refuses the files'"
            " top-level `name:`; `make compose-deps` installs v2"
        )
    raise DockerUnavailable("no docker compose (make compose-deps)")


@dataclass(frozen=True, slots=True)
class Stack:
    """One compose project: its files, in order (later ones override)."""

    compose: tuple[str, ...]
    project: str
    files: tuple[Path, ...]

    def argv(self, *args: str) -> list[str]:
        out = [*self.compose, "-p", self.project]
        for f in self.files:
            out += ["-f", str(f)]
        return [*out, *args]

    def __call__(
        self, *args: str, timeout_s: float = 180.0, check: bool = True
    ) -> subprocess.CompletedProcess[str]:
        return run(self.argv(*args), timeout_s=timeout_s, check=check)

    def logs(self, tail: int = 40) -> str:
        """The last lines of every service's log (for an assertion's message)."""
        done = self("logs", "--no-color", "--tail", str(tail), timeout_s=60, check=False)
        return done.stdout[-8000:] + done.stderr[-2000:]

    def container(self, service: str) -> str:
        """The id of the service's container (running or not)."""
        ids = self("ps", "-a", "-q", service).stdout.split()
        assert len(ids) == 1, f"{self.project}/{service}: containers {ids}"
        return ids[0]

    def inspect(self, service: str) -> dict[str, object]:
        out = run(["docker", "inspect", self.container(service)], timeout_s=30).stdout
        doc = json.loads(out)
        assert isinstance(doc, list) and len(doc) == 1
        return dict(doc[0])
