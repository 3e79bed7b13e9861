"""`telerobot record` as a process: SIGTERM finishes a complete file; SIGKILL leaves one that
reads up to its last chunk."""

from __future__ import annotations

import json
import os
import signal
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from mcap.exceptions import EndOfFile
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader

from services.bus import codec, keys
from services.bus.messages import ForceSample
from services.tools.record.archive import Recording
from services.tools.record.report import analyze
from tests.conftest import Net
from tests.tools.record.helpers import force

REPO = Path(__file__).resolve().parents[3]


def _start(net: Net, out: Path, *extra: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.tools.record",
            "-o",
            str(out),
            "--connect",
            net.endpoint,
            "--chunk-interval-s",
            "0.1",
            *extra,
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )


@pytest.fixture
def streaming(net: Net) -> Iterator[list[bytes]]:
    """Force samples on robot/force every 2 ms while the test runs; the list of payloads."""
    pub = net.node("force").publisher(keys.FORCE)
    sent: list[bytes] = []
    stop = threading.Event()

    def run() -> None:
        while not stop.wait(0.002):
            payload = force(len(sent) + 1)
            pub.put_bytes(payload)
            sent.append(payload)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    try:
        yield sent
    finally:
        stop.set()
        t.join()


def _recorded(path: Path) -> int:
    try:
        return sum(1 for _ in Recording(path).raw()) if path.exists() else 0
    except OSError:
        return 0


def _wait_recorded(path: Path, n: int, proc: subprocess.Popen[bytes]) -> None:
    deadline = time.monotonic() + 30.0
    while _recorded(path) < n:
        assert proc.poll() is None, proc.stderr.read().decode() if proc.stderr else ""
        assert time.monotonic() < deadline, "the recorder wrote no complete chunk"
        time.sleep(0.05)


def _check_prefix_of_stream(payloads: list[bytes], sent: list[bytes]) -> None:
    seqs = [codec.decode(ForceSample, p).seq for p in payloads]
    assert seqs == sorted(set(seqs))
    assert all(p == sent[s - 1] for p, s in zip(payloads, seqs, strict=True))


def test_sigkill_leaves_a_file_readable_up_to_its_last_chunk(
    net: Net, streaming: list[bytes], tmp_path: Path
) -> None:
    out = tmp_path / "killed.mcap"
    proc = _start(net, out)
    try:
        _wait_recorded(out, 50, proc)
    finally:
        proc.kill()
        proc.communicate(timeout=10.0)  # reaps it and closes its pipes
    assert proc.returncode == -signal.SIGKILL
    # No summary, no footer: the mcap library's stream reader reads up to the cut.
    n = 0
    with out.open("rb") as f, pytest.raises((EndOfFile, struct.error)):
        for record in StreamReader(f, validate_crcs=True).records:
            n += isinstance(record, Message)
    assert n > 0
    rec = Recording(out)
    payloads = [m.payload for m in rec.raw()]
    assert rec.truncated and 2 * len(payloads) == n
    _check_prefix_of_stream(payloads, streaming)
    report = analyze([out])
    assert report.truncated == [str(out)] and report.key("robot/force").count == len(payloads)


def test_sigterm_finishes_a_complete_file(net: Net, streaming: list[bytes], tmp_path: Path) -> None:
    out = tmp_path / "stopped.mcap"
    proc = _start(net, out, "--keys", "robot/**")
    try:
        _wait_recorded(out, 50, proc)
        os.kill(proc.pid, signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=30.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10.0)
    assert proc.returncode == 0, stderr.decode()
    result = json.loads(stdout.decode().strip().splitlines()[-1])
    assert result["files"] == [str(out)] and result["error"] == ""
    with out.open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == 2 * result["written"]
        assert sum(1 for _ in reader.iter_messages()) == 2 * result["written"]
    rec = Recording(out)
    payloads = [m.payload for m in rec.raw()]
    assert not rec.truncated and len(payloads) == result["written"] > 50
    _check_prefix_of_stream(payloads, streaming)
