"""The master station's configuration, read once at start-up into a frozen dataclass.

Every value is checked in `__post_init__`; a bad one raises `ConfigError("master.<key>", …)`
so a misspelt or out-of-range setting stops the service before it commands anything.
"""

from __future__ import annotations

import math
import urllib.parse
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal, get_args

import numpy as np

from services.bus.config import section
from services.bus.errors import ConfigError
from services.control.master.arm_kinematics import DEFAULT_MASTER_DH, DhRow
from services.control.master.haply_protocol import BUTTONS, DEFAULT_URL
from services.geometry import is_rotation

DeviceKind = Literal[
    "spacemouse", "serial_arm", "keyboard", "scripted", "virtual", "haply", "haptic_sim"
]
DEVICE_KINDS: tuple[str, ...] = get_args(DeviceKind)
Frame = Literal["world", "tool"]
FRAMES: tuple[str, ...] = get_args(Frame)

IDENTITY9: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)

_ID_FORBIDDEN = set("/*$?#@ ")
_MAX_NAME = 128
"""Names on the wire (`master`, `device`) are at most 128 characters."""
HAPLY_BUTTONS = len(BUTTONS)
"""The VerseGrip's buttons a, b, c are bits 0, 1, 2."""
MAX_RAMP_S = 10.0
MIN_STALE_MS, MAX_STALE_MS = 10.0, 5000.0
"""How long a wrist force may be held without a new one: from a few samples to a lease."""
_POSITIVE_KEYS = (
    "max_force_n",
    "haply_max_force_n",
    "max_torque_nm",
    "sensitivity",
    "full_speed_m_s",
    "full_rate_rad_s",
    "max_joint_torque_nm",
)


def _err(key: str, message: str) -> ConfigError:
    return ConfigError(f"master.{key}", message)


def _number(key: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise _err(key, f"must be a number, got {type(value).__name__}")
    if not math.isfinite(value):
        raise _err(key, "must be finite")
    return float(value)


MIN_DEVICE_MASS_KG, MAX_DEVICE_MASS_KG = 0.01, 20.0
"""A haptic device's moving mass at the hand: from a pen-sized stylus to a large arm."""
MIN_DEVICE_INERTIA_KG_M2, MAX_DEVICE_INERTIA_KG_M2 = 1e-5, 1.0
"""Its rotational inertia at the hand: from a stylus's roll to a large arm's wrist."""
DEVICE_INERTIA_KG_M2 = 0.002
"""The default rotational inertia at the hand (kg·m²): a 0.5 kg handle's 6 cm radius of
gyration."""


@dataclass(frozen=True, slots=True)
class MasterConfig:
    """Settings of one master station.

    master_id: the master's id on the bus (`alive/master/<id>`, `OperatorCommand.master`).
    device: which backend drives the hand pose (see `services.control.master.backends`).
    port: the device's address: serial URL for `serial_arm` (`/dev/ttyUSB0`,
        `socket://127.0.0.1:PORT`), HID path for `spacemouse` ("" = first one found),
        tty path for `keyboard` ("" = stdin); unused by `scripted`/`virtual`.
    script: for `scripted`: a trajectory file (.jsonl/.csv) or a generated motion
        (`circle`, `line`, `square`).
    rate_hz: command rate, 1–1000 Hz (the contract asks ≥ 50 Hz on `robot/cmd`).
    scale_t, scale_r: eq. 5 motion scales for translation and rotation, 0 < s ≤ 1.
    frame: `world` or `tool` (PROTOCOL §2).
    alignment: A, the master→slave axis alignment, 9 floats row-major, a rotation.
    force_scale: operator force per slave force (N/N and N·m/N·m), ≥ 0.
    max_force_n, max_torque_nm: saturation of the displayed wrench (direction kept).
    deadband: rate devices: fraction of full deflection read as zero, 0 ≤ d < 1.
    sensitivity: rate devices: multiplier on the full-deflection speeds, > 0.
    full_speed_m_s, full_rate_rad_s: rate devices: hand speed at full deflection.
    clutch_button, grip_button: bit numbers of the master-shift and grip-toggle buttons.
        For `haply` the clutch button is a dead-man: held = engaged, released =
        master-shift; bits 0, 1, 2 are the VerseGrip's a, b, c.
    engage_on_start: engage at the first tick (True) or only after the operator has
        pressed and released the master-shift (False). None: True for `scripted` and
        `virtual` masters, False for devices an operator holds.
    arm_dh: `serial_arm`: the master arm's standard DH table, 6 rows (d_m, a_m, alpha_rad).
    baudrate: `serial_arm` line speed.
    max_joint_torque_nm: `serial_arm`: clamp of each displayed joint torque.
    passivity: time-domain passivity on the displayed force (docs/passivity.md): the
        master port's energy is observed and published, and the force damped when the
        channel has no energy left to give the operator.
    passivity_device_mass_kg: the moving mass of the device (kg, at the hand) that the
        passivity force limiter predicts with; set it to your device's (a lighter device
        than assumed is accelerated more by a force step than predicted).
    passivity_moments: with passivity on, display the wrist's moment too, through a
        rotational port of its own (the moment against the hand's rotation) beside the
        force's. False (default): no moment is shown, for a device that shows none (the
        haptic masters; set it true for `serial_arm`).
    passivity_device_inertia_kg_m2: with passivity_moments, the rotational inertia of the
        device at the hand (kg·m²) the rotational port's limiter predicts with, as the
        force's does with the mass.
    force_ramp_s: the displayed wrench ramps from zero to full over this time after each
        engagement (0 = at once); it is zero whenever the master is not engaged.
    force_stale_ms: no wrist force *received* for this long and nothing is displayed (the
        last one is held until then: a lost packet or a TCP retransmission is bridged, a
        stream that stopped is not). Counted on this host's clock, never from the sample's
        robot-host stamp. 100 ms suits a LAN; over a lossy TCP link of long delay, longer.
    haply_url: `haply`: the Inverse Service's WebSocket, `ws://HOST:PORT`.
    haply_max_force_n: `haply`: the largest force ever sent to the Inverse3 (N).
    """

    master_id: str = "master"
    device: DeviceKind = "virtual"
    port: str = ""
    script: str = "circle"
    rate_hz: float = 100.0
    scale_t: float = 1.0
    scale_r: float = 1.0
    frame: Frame = "world"
    alignment: tuple[float, ...] = IDENTITY9
    force_scale: float = 1.0
    max_force_n: float = 10.0
    max_torque_nm: float = 1.0
    deadband: float = 0.05
    sensitivity: float = 1.0
    full_speed_m_s: float = 0.1
    full_rate_rad_s: float = 0.5
    clutch_button: int = 0
    grip_button: int = 1
    engage_on_start: bool | None = None
    arm_dh: tuple[DhRow, ...] = field(default=DEFAULT_MASTER_DH)
    baudrate: int = 115200
    max_joint_torque_nm: float = 1.0
    force_ramp_s: float = 0.5
    force_stale_ms: float = 100.0
    haply_url: str = DEFAULT_URL
    haply_max_force_n: float = 3.0
    passivity: bool = False
    passivity_device_mass_kg: float = 0.5
    passivity_moments: bool = False
    passivity_device_inertia_kg_m2: float = DEVICE_INERTIA_KG_M2

    def __post_init__(self) -> None:
        if not isinstance(self.master_id, str) or not self.master_id:
            raise _err("master_id", "must be a non-empty string")
        if len(self.master_id) > _MAX_NAME:
            raise _err("master_id", f"must be at most {_MAX_NAME} characters")
        if _ID_FORBIDDEN & set(self.master_id):
            raise _err("master_id", "must not contain '/', '*', '$', '?', '#', '@' or spaces")
        if self.device not in DEVICE_KINDS:
            raise _err("device", f"must be one of {', '.join(DEVICE_KINDS)}")
        for key in ("port", "script", "haply_url"):
            if not isinstance(getattr(self, key), str):
                raise _err(key, "must be a string")
        if not 1.0 <= _number("rate_hz", self.rate_hz) <= 1000.0:
            raise _err("rate_hz", "must be within 1 … 1000 Hz")
        for key in ("scale_t", "scale_r"):
            if not 0.0 < _number(key, getattr(self, key)) <= 1.0:
                raise _err(key, "must satisfy 0 < s ≤ 1")
        if self.frame not in FRAMES:
            raise _err("frame", "must be 'world' or 'tool'")
        self._check_alignment()
        if _number("force_scale", self.force_scale) < 0.0:
            raise _err("force_scale", "must be ≥ 0")
        for key in _POSITIVE_KEYS:
            if _number(key, getattr(self, key)) <= 0.0:
                raise _err(key, "must be > 0")
        if not 0.0 <= _number("deadband", self.deadband) < 1.0:
            raise _err("deadband", "must satisfy 0 ≤ d < 1")
        for key in ("clutch_button", "grip_button"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < 64:
                raise _err(key, "must be a button bit number 0 … 63")
        if self.clutch_button == self.grip_button:
            raise _err("grip_button", "must differ from clutch_button")
        if self.device == "haply":
            for key in ("clutch_button", "grip_button"):
                if getattr(self, key) >= HAPLY_BUTTONS:
                    raise _err(key, "must be 0, 1 or 2 for haply (VerseGrip a, b, c)")
        for key in ("passivity", "passivity_moments"):
            if not isinstance(getattr(self, key), bool):
                raise _err(key, "must be true or false")
        mass = _number("passivity_device_mass_kg", self.passivity_device_mass_kg)
        if not MIN_DEVICE_MASS_KG <= mass <= MAX_DEVICE_MASS_KG:
            raise _err(
                "passivity_device_mass_kg",
                f"must be within {MIN_DEVICE_MASS_KG:g} … {MAX_DEVICE_MASS_KG:g} kg",
            )
        inertia = _number("passivity_device_inertia_kg_m2", self.passivity_device_inertia_kg_m2)
        if not MIN_DEVICE_INERTIA_KG_M2 <= inertia <= MAX_DEVICE_INERTIA_KG_M2:
            raise _err(
                "passivity_device_inertia_kg_m2",
                f"must be within {MIN_DEVICE_INERTIA_KG_M2:g} … {MAX_DEVICE_INERTIA_KG_M2:g} kg·m²",
            )
        if not 0.0 <= _number("force_ramp_s", self.force_ramp_s) <= MAX_RAMP_S:
            raise _err("force_ramp_s", f"must be within 0 … {MAX_RAMP_S:g} s")
        if not MIN_STALE_MS <= _number("force_stale_ms", self.force_stale_ms) <= MAX_STALE_MS:
            raise _err("force_stale_ms", f"must be within {MIN_STALE_MS:g} … {MAX_STALE_MS:g} ms")
        self._check_url()
        if self.engage_on_start is None:
            object.__setattr__(
                self, "engage_on_start", self.device in ("scripted", "virtual", "haptic_sim")
            )
        elif not isinstance(self.engage_on_start, bool):
            raise _err("engage_on_start", "must be true or false")
        self._check_dh()
        if isinstance(self.baudrate, bool) or not isinstance(self.baudrate, int):
            raise _err("baudrate", "must be an integer")
        if self.baudrate <= 0:
            raise _err("baudrate", "must be > 0")

    def _check_url(self) -> None:
        try:
            url = urllib.parse.urlsplit(self.haply_url)
            port = url.port
        except ValueError as e:
            raise _err("haply_url", f"not a URL: {e}") from None
        if url.scheme not in ("ws", "wss") or not url.hostname or port is None:
            raise _err("haply_url", "must be ws://HOST:PORT (or wss://)")

    def _check_alignment(self) -> None:
        values = self.alignment
        if not isinstance(values, tuple | list) or len(values) != 9:
            raise _err("alignment", "must be 9 numbers (a 3×3 rotation, row-major)")
        floats = tuple(_number("alignment", v) for v in values)
        if not is_rotation(np.array(floats).reshape(3, 3)):
            raise _err("alignment", "must be a rotation (RᵀR = I within 1e-6, det R = +1)")
        object.__setattr__(self, "alignment", floats)

    def _check_dh(self) -> None:
        rows = self.arm_dh
        if not isinstance(rows, tuple | list) or len(rows) != 6:
            raise _err("arm_dh", "must be 6 rows of (d_m, a_m, alpha_rad)")
        checked: list[DhRow] = []
        for row in rows:
            if not isinstance(row, tuple | list) or len(row) != 3:
                raise _err("arm_dh", "each row must be (d_m, a_m, alpha_rad)")
            d, a, alpha = (_number("arm_dh", v) for v in row)
            checked.append((d, a, alpha))
        object.__setattr__(self, "arm_dh", tuple(checked))

    @property
    def alignment_matrix(self) -> np.ndarray:
        """A as a 3×3 array (master axes → slave axes)."""
        return np.array(self.alignment, dtype=float).reshape(3, 3)

    @property
    def period_s(self) -> float:
        """The command period, 1 / rate_hz."""
        return 1.0 / self.rate_hz

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> MasterConfig:
        """Build from a TOML table (e.g. `[master]` of a deploy file) with the bus's one
        config reader (`services.bus.config.section`): unknown keys and bad types fail
        naming `master.<key>`."""
        return section(cls, values, "master")
