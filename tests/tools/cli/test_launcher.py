"""`telerobot up`: children started with prefixed output, restarted when they crash, all
stopped on Ctrl-C/SIGTERM, and a child that cannot start makes `up` fail.

Profiles are written to tmp_path with small Python children. `launcher.run()` runs in a
thread with a Shutdown(install=False) the test sets; output is captured line by line and
awaited with deadlines.
"""

from __future__ import annotations

import io
import json
import re
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest

from services.bus.errors import ConfigError
from services.bus.lifecycle import Shutdown
from services.tools.cli import launcher
from tests.bus.test_router import spawned, telerobot
from tests.conftest import free_port, wait_until

DEADLINE_S = 20.0
PY = sys.executable

HELLO = "import time; print('hello', flush=True); time.sleep(60)"
# Lives past startup_s, then crashes; counts its runs in the file named by argv[1].
CRASHER = (
    "import pathlib, sys, time\n"
    "p = pathlib.Path(sys.argv[1])\n"
    "n = int(p.read_text()) + 1 if p.exists() else 1\n"
    "p.write_text(str(n))\n"
    "print('run', n, flush=True)\n"
    "time.sleep(0.4)\n"
    "sys.exit(3)\n"
)
FAMILY = (
    "import subprocess, sys\n"
    "g = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])\n"
    "print('grandchild', g.pid, flush=True)\n"
    "g.wait()\n"
)
STUBBORN = (
    "import signal, time\n"
    "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
    "print('ignoring SIGTERM', flush=True)\n"
    "time.sleep(60)\n"
)


class Output(io.StringIO):
    """The launcher's `out`: lines kept in order, awaitable until the launcher has returned."""

    def __init__(self) -> None:
        super().__init__()
        self._cond = threading.Condition()
        self.lines: list[str] = []
        self._partial = ""
        self._finished = False

    def write(self, s: str) -> int:
        with self._cond:
            text = self._partial + s
            *done, self._partial = text.split("\n")
            self.lines.extend(done)
            self._cond.notify_all()
        return len(s)

    def finish(self) -> None:
        """The launcher returned: nothing more will come, so waits fail at once."""
        with self._cond:
            self._finished = True
            self._cond.notify_all()

    def wait_for(self, pred: Callable[[str], bool], timeout_s: float = DEADLINE_S) -> str:
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                for line in self.lines:
                    if pred(line):
                        return line
                left = deadline - time.monotonic()
                if left <= 0 or self._finished:
                    raise AssertionError(f"no such line in {self.lines}")
                self._cond.wait(left)

    def wait_line(self, text: str, timeout_s: float = DEADLINE_S) -> str:
        return self.wait_for(lambda line: text in line, timeout_s)

    def snapshot(self) -> list[str]:
        with self._cond:
            return list(self.lines)


def profile(tmp_path: Path, commands: dict[str, list[str]], **up: object) -> Path:
    """A deployment TOML with an [up] table (JSON strings are valid TOML basic strings)."""
    lines = ["[up]"]
    lines += [f"{k} = {json.dumps(v)}" for k, v in up.items()]
    lines.append("[up.commands]")
    lines += [
        f"{name} = [{', '.join(json.dumps(a) for a in argv)}]" for name, argv in commands.items()
    ]
    p = tmp_path / "profile.toml"
    p.write_text("\n".join(lines) + "\n")
    return p


def pid_gone(pid: int) -> bool:
    """No such process, or a zombie only waiting for a reaper."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return True
    return state in ("Z", "X")


def all_gone(pids: list[int]) -> bool:
    return all(pid_gone(p) for p in pids)


def started_pids(lines: list[str], name: str) -> list[int]:
    pat = re.compile(rf"^\[{name}\] started pid (\d+) \(start #\d+\)$")
    return [int(m.group(1)) for line in lines if (m := pat.match(line))]


@dataclass
class Launch:
    """A launcher.run() in a thread: its output, its stop flag, and what it returned."""

    out: Output
    stop: Shutdown
    status: int | None = None
    error: BaseException | None = None


@contextmanager
def running(path: Path, overrides: launcher.Overrides | None = None) -> Iterator[Launch]:
    """launcher.run(path) in a thread; stopped and joined on exit."""
    launch = Launch(Output(), Shutdown(install=False))

    def target() -> None:
        try:
            launch.status = launcher.run(
                path, launch.out, launch.stop, overrides or launcher.Overrides()
            )
        except BaseException as e:  # handed to the test thread, which re-raises it
            launch.error = e
        finally:
            launch.out.finish()

    t = threading.Thread(target=target)
    t.start()
    try:
        yield launch
    finally:
        launch.stop.set()
        t.join(DEADLINE_S)
        assert not t.is_alive(), "launcher did not stop"
        if launch.error is not None:
            raise launch.error


def test_up_starts_restarts_and_stops_everything(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    path = profile(
        tmp_path,
        {
            "hello": [PY, "-c", HELLO],
            "crasher": [PY, "-c", CRASHER, str(runs)],
            "family": [PY, "-c", FAMILY],
        },
        startup_s=0.2,
        backoff_s=0.1,
        backoff_max_s=0.2,
        stop_timeout_s=5.0,
    )
    with running(path) as launch:
        out = launch.out
        out.wait_line("[hello] hello")
        out.wait_line("[crasher] run 1")
        grandchild = int(out.wait_line("[family] grandchild").split()[-1])
        out.wait_for(lambda line: line.startswith("[crasher] started") and "(start #3)" in line)
        out.wait_line("[crasher] run 3")
        launch.stop.set()
    lines = out.snapshot()
    assert launch.status == 0

    # every output line is prefixed with its child's name
    assert all(re.match(r"^\[(hello|crasher|family)\] ", line) for line in lines), lines
    # the crashing child was restarted with growing, capped backoff
    restarts = [line for line in lines if line.startswith("[crasher] exited with 3")]
    assert restarts[:2] == [
        "[crasher] exited with 3; restarting in 0.1 s",
        "[crasher] exited with 3; restarting in 0.2 s",
    ]
    assert int(runs.read_text()) >= 3
    crasher_pids = started_pids(lines, "crasher")
    assert len(crasher_pids) >= 3 and len(set(crasher_pids)) == len(crasher_pids)
    # hello and family were started once and never restarted
    assert len(started_pids(lines, "hello")) == 1 and len(started_pids(lines, "family")) == 1
    # stopping killed every child and the grandchild (its process group)
    pids = started_pids(lines, "hello") + started_pids(lines, "family") + crasher_pids
    assert wait_until(lambda: all_gone([*pids, grandchild]))
    assert f"[hello] stopped (exit {-signal.SIGTERM})" in lines
    assert any(line.startswith("[family] stopped (exit") for line in lines)


def test_a_child_that_cannot_start_makes_up_fail(tmp_path: Path) -> None:
    path = profile(
        tmp_path,
        {
            "hello": [PY, "-c", HELLO],
            "broken": [PY, "-c", "import sys; print('no device', flush=True); sys.exit(1)"],
        },
        startup_s=5.0,
    )
    out, stop = Output(), Shutdown(install=False)
    status = launcher.run(path, out, stop)  # returns on its own: no stop needed
    lines = out.snapshot()
    assert status == 1
    assert "[broken] no device" in lines
    assert "[broken] could not start (exit 1); stopping everything" in lines
    assert any(line.startswith("[hello] stopped (exit") for line in lines)
    assert wait_until(lambda: all_gone(started_pids(lines, "hello")))
    assert len(started_pids(lines, "broken")) == 1  # not restarted


def test_without_restart_a_finished_child_is_reported_once(tmp_path: Path) -> None:
    path = profile(
        tmp_path,
        {
            "hello": [PY, "-c", HELLO],
            "oneshot": [PY, "-c", "import time; time.sleep(0.3); print('done', flush=True)"],
        },
        startup_s=0.1,
        restart=False,
    )
    with running(path) as launch:
        out = launch.out
        out.wait_line("[oneshot] exited with 0; not restarting")
        out.wait_line("[hello] hello")
        # An observation window, not synchronisation: the supervisor polls every 50 ms, and
        # a finished child must not be reported again on any of those rounds.
        launch.stop.wait(0.5)
    lines = out.snapshot()
    assert launch.status == 0
    assert lines.count("[oneshot] exited with 0; not restarting") == 1
    assert len(started_pids(lines, "oneshot")) == 1


def test_a_child_that_ignores_sigterm_is_killed(tmp_path: Path) -> None:
    path = profile(tmp_path, {"stubborn": [PY, "-c", STUBBORN]}, stop_timeout_s=0.5)
    with running(path) as launch:
        out = launch.out
        out.wait_line("[stubborn] ignoring SIGTERM")
    lines = out.snapshot()
    assert launch.status == 0
    assert "[stubborn] did not stop in time; killing" in lines
    assert f"[stubborn] stopped (exit {-signal.SIGKILL})" in lines
    assert wait_until(lambda: all_gone(started_pids(lines, "stubborn")))


def test_telerobot_up_stops_its_children_on_sigterm(tmp_path: Path) -> None:
    path = profile(tmp_path, {"hello": [PY, "-c", HELLO], "family": [PY, "-c", FAMILY]})
    with spawned(telerobot("up", str(path))) as up:
        up.expect("[hello] hello")
        grandchild = int(up.expect("[family] grandchild").split()[-1])
        up.proc.send_signal(signal.SIGTERM)
        assert up.wait(DEADLINE_S) == 0
        lines = up.rest()
    pids = started_pids(lines, "hello") + started_pids(lines, "family")
    assert len(pids) == 2
    assert wait_until(lambda: all_gone([*pids, grandchild]))
    assert any(line.startswith("[hello] stopped (exit") for line in lines)


def test_service_names_become_telerobot_subcommands(tmp_path: Path) -> None:
    path = tmp_path / "p.toml"
    cfg = launcher.UpConfig(services=("router", "arm"), args={"arm": ["--sim"]})
    assert launcher.child_argv("arm", path, cfg) == [
        PY,
        "-m",
        "services.tools.cli.main",
        "arm",
        "--config",
        str(path),
        "--sim",
    ]
    cfg = launcher.UpConfig(commands={"rec": ["telerobot", "record"]})
    assert launcher.child_argv("rec", path, cfg) == ["telerobot", "record"]


@pytest.mark.parametrize(
    ("table", "key"),
    [
        ("[up]\n", "up.services"),
        ('[up]\nservices = ["arm"]\nbogus = 1\n', "up.bogus"),
        ('[up]\nservices = ["arm"]\nbackoff_s = 0\n', "up.backoff_s"),
        ('[up]\nservices = ["arm"]\n[up.args]\narm = "--sim"\n', "up.args.arm"),
        ("[up]\n[up.commands]\nx = []\n", "up.commands.x"),
        ('[up]\n[up.commands]\nx = ["python", 1]\n', "up.commands.x"),
    ],
)
def test_a_bad_up_table_is_refused_before_anything_starts(
    tmp_path: Path, table: str, key: str
) -> None:
    p = tmp_path / "bad.toml"
    p.write_text(table)
    with pytest.raises(ConfigError) as info:
        launcher.run(p, Output(), Shutdown(install=False))
    assert info.value.key == key


def test_an_unknown_profile_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert launcher.main([str(tmp_path / "nope")]) == 2
    assert "no profile" in capsys.readouterr().err
    p = tmp_path / "mine.toml"
    p.write_text('[up]\nservices = ["arm"]\n')
    assert launcher.resolve_profile(str(p)) == p


def test_children_die_with_a_killed_launcher(tmp_path: Path) -> None:
    path = profile(tmp_path, {"hello": [PY, "-c", HELLO]})
    with spawned(telerobot("up", str(path))) as up:
        up.expect("[hello] hello")
        pids = started_pids(up.lines, "hello")
        up.proc.send_signal(signal.SIGKILL)
        up.wait(DEADLINE_S)
    assert len(pids) == 1
    assert wait_until(lambda: all_gone(pids)), "a child outlived its SIGKILLed launcher"


# --- issue 23, items 5 and 6 -------------------------------------------------------------

CONFIG_TYPO = (
    "import sys, time\n"
    "time.sleep(0.5)\n"  # past startup_s: the startup rule is not what stops the launch
    "print('telerobot arm: arm.bogus: unknown key (known: arm, port)', file=sys.stderr)\n"
    "sys.exit(2)\n"
)


def test_a_configuration_error_stops_everything_and_names_the_key(tmp_path: Path) -> None:
    path = profile(
        tmp_path,
        {"hello": [PY, "-c", HELLO], "typo": [PY, "-c", CONFIG_TYPO]},
        startup_s=0.1,
        backoff_s=0.1,
        backoff_max_s=0.1,
    )
    out, stop = Output(), Shutdown(install=False)
    status = launcher.run(path, out, stop)  # returns on its own: no stop needed
    lines = out.snapshot()
    assert status == 1
    assert (
        "[typo] configuration error (exit 2): telerobot arm: arm.bogus: unknown key "
        "(known: arm, port); stopping everything"
    ) in lines
    assert len(started_pids(lines, "typo")) == 1  # never restarted
    assert not any("restarting" in line for line in lines)
    assert any(line.startswith("[hello] stopped (exit") for line in lines)
    assert wait_until(lambda: all_gone(started_pids(lines, "hello")))


def test_a_real_service_with_a_misspelt_key_fails_the_launch(tmp_path: Path) -> None:
    """The real arm, its import included (seconds under load): exit 2 names `arm.bogus`."""
    path = tmp_path / "typo.toml"
    path.write_text('[arm]\ndriver = "sim"\nbogus = 1\n[up]\nservices = ["arm"]\n')
    out, stop = Output(), Shutdown(install=False)
    status = launcher.run(path, out, stop)
    lines = out.snapshot()
    assert status == 1
    fatal = [line for line in lines if "configuration error (exit 2)" in line]
    assert len(fatal) == 1 and fatal[0].startswith("[arm] ") and "arm.bogus" in fatal[0]
    assert len(started_pids(lines, "arm")) == 1


def test_a_child_dying_during_a_slow_start_up_stops_everything(tmp_path: Path) -> None:
    """With the default startup_s, a child that dies after 1.5 s (an import under load
    takes 3–13 s) still counts as one that could not start: the old 1 s missed it."""
    assert launcher.UpConfig(services=("arm",)).startup_s >= 20.0
    slow_death = "import sys, time; time.sleep(1.5); print('no device', flush=True); sys.exit(1)"
    path = profile(tmp_path, {"hello": [PY, "-c", HELLO], "slow": [PY, "-c", slow_death]})
    out, stop = Output(), Shutdown(install=False)
    assert launcher.run(path, out, stop) == 1
    lines = out.snapshot()
    assert "[slow] could not start (exit 1); stopping everything" in lines
    assert len(started_pids(lines, "slow")) == 1


def test_the_stop_sequence_fits_in_the_exit_grace(tmp_path: Path) -> None:
    """Children stop one by one, each up to stop_timeout_s: the last-resort thread dump of
    a SIGTERMed launcher must wait longer than that sequence can take."""
    path = profile(tmp_path, {f"c{i}": [PY, "-c", HELLO] for i in range(4)}, stop_timeout_s=6.0)
    with running(path) as launch:
        launch.out.wait_line("[c3] hello")
        assert launch.stop.grace_s >= 4 * 6.0


def test_sigterm_stops_up_cleanly_without_a_thread_dump(tmp_path: Path) -> None:
    slow_stop = (
        "import signal, sys, time\n"
        "signal.signal(signal.SIGTERM, lambda *a: (time.sleep(1.0), sys.exit(0)))\n"
        "print('ready', flush=True)\n"
        "time.sleep(60)\n"
    )
    path = profile(tmp_path, {"a": [PY, "-c", slow_stop], "b": [PY, "-c", slow_stop]})
    with spawned(telerobot("up", str(path))) as up:
        up.expect("[a] ready")
        up.expect("[b] ready")
        up.proc.send_signal(signal.SIGTERM)
        assert up.wait(DEADLINE_S) == 0
        lines = up.rest()
    assert "[b] stopped (exit 0)" in lines and lines[-1] == "[a] stopped (exit 0)"
    text = "\n".join(lines)
    for dump in ("Traceback", "Thread 0x", "Current thread", "Fatal Python error"):
        assert dump not in text, lines


def listening(port: int) -> socket.socket:
    """A listener on 127.0.0.1:port standing in for a running Telerobot's router."""
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.bind(("127.0.0.1", port))
    s.listen()
    return s


def router_profile(tmp_path: Path, port: int) -> Path:
    p = tmp_path / "two.toml"
    p.write_text(
        f'[router]\nlisten = ["tcp/127.0.0.1:{port}"]\n'
        '[up]\nservices = ["router"]\n'
        f"[up.commands]\nhello = {json.dumps([PY, '-c', HELLO])}\n"
    )
    return p


def test_a_second_launch_is_refused_before_anything_starts(tmp_path: Path) -> None:
    port = free_port()
    path = router_profile(tmp_path, port)
    with listening(port), spawned(telerobot("up", str(path)), merge_stderr=False) as up:
        assert up.wait(DEADLINE_S) == 1
        lines = up.rest()
    assert lines == []  # no service started, not even the router
    assert up.errors == [
        f"telerobot up: a router already listens on {port}; another Telerobot is running — "
        "stop it or use --listen/--ns"
    ]


def test_the_demo_refuses_a_second_run_before_anything_starts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from services.tools.cli import demo

    port = free_port()
    path = router_profile(tmp_path, port)
    with listening(port):
        assert demo.main(["--profile", str(path), "--task", "none"]) == 1
    out, err = capsys.readouterr()
    assert out == ""
    assert err == (
        f"telerobot demo: a router already listens on {port}; another Telerobot is running — "
        "stop it or use --listen/--ns\n"
    )


def test_with_a_namespace_a_second_launch_joins_the_running_router(tmp_path: Path) -> None:
    port = free_port()
    path = router_profile(tmp_path, port)
    with listening(port), running(path, launcher.Overrides(ns="cell2")) as launch:
        launch.out.wait_line("[hello] hello")
        lines = launch.out.snapshot()
    assert lines[0] == (
        f"[up] a router already listens on tcp/127.0.0.1:{port}: joining it under namespace "
        "'cell2' (no router of our own)"
    )
    assert started_pids(lines, "router") == []


def test_a_free_port_is_not_taken_and_listen_moves_the_router(tmp_path: Path) -> None:
    port, other = free_port(), free_port()
    deploy = {"router": {"listen": [f"tcp/127.0.0.1:{port}"]}}
    assert launcher.taken_router_endpoints(deploy, launcher.Overrides()) == []
    with listening(port):
        assert launcher.taken_router_endpoints(deploy, launcher.Overrides()) == [
            f"tcp/127.0.0.1:{port}"
        ]
        moved = launcher.Overrides(listen=f"tcp/127.0.0.1:{other}")
        assert launcher.taken_router_endpoints(deploy, moved) == []
    assert launcher.router_endpoints({}, launcher.Overrides()) == ["tcp/0.0.0.0:7447"]
    assert launcher.endpoint_taken("tls/127.0.0.1:7448") is False  # not checked
    assert launcher.endpoint_taken("tcp/127.0.0.1:0") is False


def test_listen_and_ns_reach_every_service(tmp_path: Path) -> None:
    path = tmp_path / "p.toml"
    cfg = launcher.UpConfig(services=("router", "arm"), commands={"rec": ["x"]})
    o = launcher.Overrides(listen="tcp/0.0.0.0:7450", ns="cell2")
    assert launcher.child_argv("router", path, cfg, o)[-2:] == ["--listen", "tcp/0.0.0.0:7450"]
    assert launcher.child_argv("arm", path, cfg, o)[-4:] == [
        "--connect",
        "tcp/127.0.0.1:7450",
        "--ns",
        "cell2",
    ]
    assert launcher.child_argv("rec", path, cfg, o) == ["x"]
    for bad in ("7450", "udp/1.2.3.4:5", "tcp/127.0.0.1:port"):
        with pytest.raises(ConfigError) as info:
            launcher.Overrides(listen=bad)
        assert info.value.key == "--listen"
    with pytest.raises(ConfigError):
        launcher.Overrides(ns="a/*")


def test_a_router_on_a_taken_port_says_so_without_a_traceback() -> None:
    """Two launches started at once both pass the launcher's check; the second router then
    finds its port taken and exits 1 with the same sentence (no Rust traceback), which
    stops its launch as a child that could not start."""
    port = free_port()
    argv = telerobot("router", "--listen", f"tcp/127.0.0.1:{port}")
    with listening(port), spawned(argv, merge_stderr=False) as router:
        assert router.wait(DEADLINE_S) == 1
        lines = router.rest()
    assert lines == []
    assert router.errors == [
        f"telerobot router: a router already listens on {port}; another Telerobot is "
        "running — stop it or use --listen/--ns"
    ]
