"""Scripted and virtual masters: file formats, playback, generated motions end to end."""

from __future__ import annotations

import json
import math
import threading
from pathlib import Path

import numpy as np
import pytest

from services.control.master.config import MasterConfig
from services.control.master.devices.scripted import (
    ScriptedMaster,
    Trajectory,
    TrajectoryError,
    TrajectorySample,
    generate_motion,
    load_trajectory,
    save_trajectory,
)
from services.control.master.devices.virtual import VirtualMaster
from services.control.master.teleop import Teleop
from services.geometry import exp_so3, rot_z

JSONL = """\
{"t": 0.0, "p": [0.0, 0.0, 0.0]}
{"t": 1.0, "p": [0.1, 0.0, 0.0], "R": [0, -1, 0, 1, 0, 0, 0, 0, 1], "grip": 0.5}

{"t": 2.0, "p": [0.1, 0.2, 0.0], "w": [0, 0, 1.5707963267948966], "clutch": true, "grip": 1.0}
"""

CSV = """\
# a hand-written trajectory
t, px, py, pz, wx, wy, wz, clutch, grip
0.0, 0.0, 0.0, 0.0, 0, 0, 0, 0,
1.0, 0.1, 0.0, 0.0, 0, 0, 1.5707963267948966, 0, 0.5
2.0, 0.1, 0.2, 0.0, 0, 0, 1.5707963267948966, 1, 1.0
"""


@pytest.mark.parametrize(("name", "text"), [("hand.jsonl", JSONL), ("hand.csv", CSV)])
def test_plays_a_file(tmp_path: Path, name: str, text: str) -> None:
    path = tmp_path / name
    path.write_text(text)
    m = ScriptedMaster(path)
    m.open()
    assert m.name == f"scripted:{name}"
    r0 = m.read(0.0)
    np.testing.assert_array_equal(r0.hand_p, [0, 0, 0])
    assert r0.clutch is False and r0.grip is None
    r = m.read(0.5)  # halfway through the first segment
    np.testing.assert_allclose(r.hand_p, [0.05, 0, 0], atol=1e-12)
    np.testing.assert_allclose(r.hand_R, rot_z(math.pi / 4), atol=1e-12)
    assert r.grip is None  # held from the earlier sample
    r = m.read(0.75)  # t = 1.25
    np.testing.assert_allclose(r.hand_p, [0.1, 0.05, 0], atol=1e-12)
    assert (r.clutch, r.grip) == (False, 0.5)
    r = m.read(5.0)  # past the end: the last sample
    np.testing.assert_allclose(r.hand_p, [0.1, 0.2, 0])
    assert (r.clutch, r.grip, m.finished) == (True, 1.0, True)


def test_format_is_sniffed_without_a_known_suffix(tmp_path: Path) -> None:
    (tmp_path / "a.txt").write_text(JSONL)
    (tmp_path / "b.txt").write_text(CSV)
    assert load_trajectory(tmp_path / "a.txt").duration_s == 2.0
    assert load_trajectory(tmp_path / "b.txt").duration_s == 2.0


def test_save_and_load_round_trip(tmp_path: Path) -> None:
    traj = generate_motion("square", size_m=0.05, period_s=2.0, cycles=1)
    save_trajectory(tmp_path / "sq.jsonl", traj)
    back = load_trajectory(tmp_path / "sq.jsonl")
    assert back.samples == traj.samples
    first = json.loads((tmp_path / "sq.jsonl").read_text().splitlines()[0])
    assert set(first) == {"t", "p", "R", "clutch", "grip"}


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('{"t": 0, "p": [0, 0, 0]}\n{"t": 0, "p": [0, 0, 0]}\n', "strictly increase"),
        ('{"t": 0, "p": [0, 0]}\n', "p must be 3"),
        ('{"t": 0, "p": [0, 0, 0], "R": [1, 0, 0, 0, 1, 0, 0, 0, 2]}\n', "rotation"),
        ('{"t": 0, "p": [0, 0, 0], "grip": 2}\n', "grip"),
        ('{"t": 0, "p": [0, 0, 0], "clutch": "maybe"}\n', "clutch"),
        ('{"p": [0, 0, 0]}\n', "missing field"),
        ("[1, 2]\n", "JSON object"),
        ("{oops\n", ":1:"),
        ("", "at least one"),
    ],
)
def test_bad_jsonl_is_refused_with_its_line(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.jsonl"
    path.write_text(text)
    with pytest.raises(TrajectoryError, match=message):
        load_trajectory(path)


def test_bad_csv_header_and_missing_file(tmp_path: Path) -> None:
    (tmp_path / "bad.csv").write_text("t,x,y,z\n0,0,0,0\n")
    with pytest.raises(TrajectoryError, match="px, py, pz"):
        load_trajectory(tmp_path / "bad.csv")
    with pytest.raises(TrajectoryError, match="cannot read"):
        load_trajectory(tmp_path / "absent.csv")


def test_loop_wraps_with_one_master_shift_tick() -> None:
    traj = Trajectory(
        [TrajectorySample.make(0.0, (0, 0, 0)), TrajectorySample.make(1.0, (0.1, 0, 0))]
    )
    m = ScriptedMaster(traj, loop=True)
    m.open()
    assert m.read(0.9).clutch is False
    wrapped = m.read(0.2)  # t = 1.1 → 0.1
    assert wrapped.clutch is True
    np.testing.assert_allclose(wrapped.hand_p, [0.01, 0, 0], atol=1e-12)
    assert m.read(0.1).clutch is False and not m.finished


def test_set_hand_takes_over_from_the_script() -> None:
    m = ScriptedMaster("circle")
    m.open()
    m.read(0.5)
    m.set_hand((1.0, 2.0, 3.0), rot_z(0.3), clutch=True, grip=0.2)
    r = m.read(0.5)
    np.testing.assert_allclose(r.hand_p, [1, 2, 3])
    assert (r.clutch, r.grip) == (True, 0.2)


def test_virtual_master_is_thread_safe_and_validates() -> None:
    v = VirtualMaster()
    v.open()
    with pytest.raises(ValueError):
        v.set_hand((0, 0, 0), 2 * np.eye(3))
    with pytest.raises(ValueError):
        v.set_hand((0, 0, math.nan))

    def writer(k: int) -> None:
        for i in range(200):
            v.set_hand((k, i, 0), exp_so3([0, 0, 0.01 * i]), clutch=bool(i % 2))

    threads = [threading.Thread(target=writer, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for _ in range(200):
        r = v.read(0.01)  # never a torn reading: p and R always from one set_hand
        assert r.hand_R.shape == (3, 3) and r.hand_p.shape == (3,)
    for t in threads:
        t.join()
    last = v.read(0.0)
    assert last.hand_p[1] == 199
    v.display_force((1, 2, 3), (0, 0, 0.5))
    f, c = v.displayed_force()
    np.testing.assert_array_equal(f, [1, 2, 3])
    np.testing.assert_array_equal(c, [0, 0, 0.5])


# --- generated motions through the teleoperation core and PROTOCOL §2's slave ---------------


def run_slave(master: ScriptedMaster, cfg: MasterConfig, dt_s: float = 0.01) -> tuple[list, list]:
    """Play the master to its end through Teleop; return hand and slave positions."""
    t = Teleop(cfg, master.name, seq_start=0, engage_start=0)
    slave_p, p0, engage = np.zeros(3), np.zeros(3), None
    hands, slaves = [], []
    master.open()
    k = 0
    while not master.finished:
        reading = master.read(0.0 if k == 0 else dt_s)
        cmd = t.tick(reading, k)
        if cmd.active:
            if cmd.engage != engage:
                engage, p0 = cmd.engage, slave_p.copy()
            slave_p = p0 + np.array(cmd.dp)
        hands.append(reading.hand_p.copy())
        slaves.append(slave_p.copy())
        k += 1
    return hands, slaves


def test_line_ratchet_advances_the_slave_while_the_hand_returns() -> None:
    master = ScriptedMaster("line", size_m=0.1, period_s=1.0, cycles=3)
    hands, slaves = run_slave(master, MasterConfig(device="scripted", scale_t=0.5))
    np.testing.assert_allclose(hands[-1], [0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(slaves[-1], [3 * 0.1 * 0.5, 0, 0], atol=1e-9)
    steps = np.linalg.norm(np.diff(np.array(slaves), axis=0), axis=1)
    hand_steps = np.linalg.norm(np.diff(np.array(hands), axis=0), axis=1)
    assert np.all(steps <= 0.5 * hand_steps + 1e-12)
    assert np.all(np.diff(np.array(slaves)[:, 0]) >= -1e-12)  # the slave never goes back


def test_square_with_hand_rising_in_master_shift_keeps_the_slave_flat() -> None:
    master = ScriptedMaster("square", size_m=0.1, period_s=2.0, cycles=1)
    hands, slaves = run_slave(master, MasterConfig(device="scripted"))
    assert hands[-1][2] == pytest.approx(0.08)
    assert max(abs(s[2]) for s in slaves) < 1e-12
    np.testing.assert_allclose(slaves[-1], [0, 0, 0], atol=1e-9)
    xs = [s[0] for s in slaves]
    assert max(xs) == pytest.approx(0.1)


def test_circle_closes_and_turns_the_wrist() -> None:
    traj = generate_motion("circle", size_m=0.2, period_s=2.0, cycles=1)
    end = traj.sample(traj.duration_s)
    np.testing.assert_allclose(end.hand_p, [0, 0, 0], atol=1e-12)
    quarter = traj.sample(0.5)
    np.testing.assert_allclose(quarter.hand_p, [-0.1, 0.1, 0], atol=1e-3)
    assert not any(s.clutch for s in traj.samples)


def test_unknown_generated_motion() -> None:
    with pytest.raises(TrajectoryError):
        generate_motion("spiral")
    with pytest.raises(TrajectoryError):
        generate_motion("line", size_m=-1.0)
