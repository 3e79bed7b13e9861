"""The block of memory the arm service and its real-time process share: the newest joint
setpoint one way, the robot's newest state the other, each without a lock or a system call.

Why a process and shared memory: pylibfranka keeps Python's interpreter lock while it waits
in `readOnce` (measured here: a second thread of the same process woke ~150 times a second
instead of 2 000 while the loop ran), so the 1 kHz loop cannot share a process with the
arm service's bus callbacks. The block is a file in /dev/shm (a tmpfs), mapped by both.

Each half has one writer and is a seqlock: the writer makes the counter odd, writes, makes
it even; a reader copies and retries while the counter was odd or changed. float64 slots
(counters too: exact to 2⁵³); 8-byte aligned stores are atomic on the machines libfranka
runs on (x86-64, aarch64).
"""

from __future__ import annotations

import contextlib
import mmap
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

N = 7
RING = 4096
"""Cycle periods kept (s, the loop's own wall clock), for the bench's jitter figures."""

# --- the command half (the arm service writes) -------------------------------------------
C_SEQ = 0  # seqlock
C_SP_SEQ = 1  # setpoint number (the n-th command)
C_HOLD = 2  # hold requests: the interpolator brakes to rest where it is
C_SP = 3  # the setpoint, N joints (rad)
C_SP_T = C_SP + N  # when it was written (time.monotonic_ns of the writer, as float)
C_END = C_SP_T + 1

# --- the state half (the real-time process writes) ---------------------------------------
S_SEQ = C_END
S_CYCLES = S_SEQ + 1  # control cycles run (readOnce/writeOnce pairs)
S_LOST = S_SEQ + 2  # cycles the robot's clock says were missed (duration > 1 ms)
S_T_ROBOT = S_SEQ + 3  # the robot's clock, sum of readOnce durations (s)
S_MODE = S_SEQ + 4  # franka::RobotMode as its int (0 other … 6 automatic error recovery)
S_CONTROLLING = S_SEQ + 5  # 1 while the joint position loop runs
S_WALL_NS = S_SEQ + 6  # time.monotonic_ns of the last write, as float
S_SP_SEQ = S_SEQ + 7  # the setpoint number the interpolator aims at
S_SP_T = S_SEQ + 8  # when the loop first aimed at it (monotonic ns)
S_Q = S_SEQ + 9
S_DQ = S_Q + N
S_QC = S_DQ + N  # what the loop commanded this cycle
S_O_T_EE = S_QC + N  # 16, column-major as libfranka
S_F_EXT = S_O_T_EE + 16  # O_F_ext_hat_K: 6, base frame, at the stiffness frame K
S_EE_T_K = S_F_EXT + 6  # 16
S_F_T_EE = S_EE_T_K + 16  # 16
S_RING_I = S_F_T_EE + 16  # next ring slot (count of periods written)
S_RING = S_RING_I + 1
S_END = S_RING + RING
SIZE = S_END * 8

Vec = NDArray[np.float64]


def _where() -> str | None:
    return "/dev/shm" if os.path.isdir("/dev/shm") else None


def state_path(robot_ip: str) -> Path:
    """Where the arm's libfranka driver keeps the block of the robot at `robot_ip` on this
    host (the franka force source reads it there)."""
    safe = "".join(c if c.isalnum() or c in ".-" else "_" for c in robot_ip)[:64]
    return Path(_where() or tempfile.gettempdir()) / f"telerobot-franka-{safe}.shm"


@dataclass(frozen=True, slots=True)
class Snapshot:
    """One consistent copy of the state half."""

    cycles: int
    lost: int
    t_robot_s: float
    mode: int
    controlling: bool
    wall_ns: int
    sp_seq: int
    sp_t_ns: int
    q: Vec
    dq: Vec
    q_cmd: Vec
    O_T_EE: Vec
    O_F_ext_hat_K: Vec
    EE_T_K: Vec
    F_T_EE: Vec


class Shared:
    """The mapped block (`create()` in the arm service, `attach(path)` in the RT process)."""

    def __init__(self, path: Path, owner: bool) -> None:
        self.path = path
        self._owner = owner
        fd = os.open(path, os.O_RDWR)
        try:
            self._mm = mmap.mmap(fd, SIZE)
        finally:
            os.close(fd)
        self.a: Vec = np.frombuffer(self._mm, dtype=np.float64, count=S_END)

    @classmethod
    def create(cls, path: Path | None = None) -> Shared:
        """A fresh zeroed block at `path` (default: a new file in /dev/shm, or the temp dir
        where there is none); an old one there (a crashed run's) is replaced."""
        if path is None:
            fd, name = tempfile.mkstemp(prefix="telerobot-franka-", suffix=".shm", dir=_where())
            path = Path(name)
        else:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            os.ftruncate(fd, SIZE)
        finally:
            os.close(fd)
        return cls(path, owner=True)

    @classmethod
    def attach(cls, path: str | Path) -> Shared:
        return cls(Path(path), owner=False)

    def close(self, unlink: bool = True) -> None:
        """Unmap; the owner also removes the file unless `unlink` is false."""
        a = self.a
        self.a = np.zeros(S_END)
        del a
        # a view may still be alive somewhere: then the mapping goes with the process
        with contextlib.suppress(BufferError):
            self._mm.close()
        if self._owner and unlink:
            self.path.unlink(missing_ok=True)

    # --- the command half ----------------------------------------------------------------
    def put_setpoint(self, q: list[float], t_ns: int) -> int:
        """Publish setpoint `q` (the writer is the arm service); its number."""
        a = self.a
        a[C_SEQ] += 1.0
        seq = int(a[C_SP_SEQ]) + 1
        a[C_SP : C_SP + N] = q
        a[C_SP_T] = float(t_ns)
        a[C_SP_SEQ] = float(seq)
        a[C_SEQ] += 1.0
        return seq

    def request_hold(self) -> None:
        a = self.a
        a[C_SEQ] += 1.0
        a[C_HOLD] += 1.0
        a[C_SEQ] += 1.0

    def get_command(self) -> tuple[int, int, list[float], int]:
        """(setpoint number, hold requests, setpoint, its time ns), consistent."""
        a = self.a
        while True:
            s0 = a[C_SEQ]
            if s0 % 2.0 == 0.0:
                sp_seq, hold = int(a[C_SP_SEQ]), int(a[C_HOLD])
                q = a[C_SP : C_SP + N].tolist()
                t = int(a[C_SP_T])
                if a[C_SEQ] == s0:
                    return sp_seq, hold, q, t

    # --- the state half ------------------------------------------------------------------
    def begin_state(self) -> Vec:
        self.a[S_SEQ] += 1.0
        return self.a

    def end_state(self) -> None:
        self.a[S_SEQ] += 1.0

    def state_seq(self) -> float:
        return float(self.a[S_SEQ])

    def snapshot(self) -> Snapshot:
        a = self.a
        while True:
            s0 = a[S_SEQ]
            if s0 % 2.0 == 0.0:
                c = a[S_SEQ:S_RING_I].copy()
                if a[S_SEQ] == s0:
                    break
        o = -S_SEQ
        return Snapshot(
            cycles=int(c[S_CYCLES + o]),
            lost=int(c[S_LOST + o]),
            t_robot_s=float(c[S_T_ROBOT + o]),
            mode=int(c[S_MODE + o]),
            controlling=bool(c[S_CONTROLLING + o]),
            wall_ns=int(c[S_WALL_NS + o]),
            sp_seq=int(c[S_SP_SEQ + o]),
            sp_t_ns=int(c[S_SP_T + o]),
            q=c[S_Q + o : S_Q + o + N],
            dq=c[S_DQ + o : S_DQ + o + N],
            q_cmd=c[S_QC + o : S_QC + o + N],
            O_T_EE=c[S_O_T_EE + o : S_O_T_EE + o + 16],
            O_F_ext_hat_K=c[S_F_EXT + o : S_F_EXT + o + 6],
            EE_T_K=c[S_EE_T_K + o : S_EE_T_K + o + 16],
            F_T_EE=c[S_F_T_EE + o : S_F_T_EE + o + 16],
        )

    def periods(self) -> Vec:
        """The loop's last cycle periods (s), oldest first (at most RING)."""
        a = self.a
        k = int(a[S_RING_I])
        ring = a[S_RING : S_RING + RING].copy()
        if k <= RING:
            return ring[:k]
        i = k % RING
        return np.concatenate([ring[i:], ring[:i]])
