"""The master station's configuration, read once at start-up into frozen dataclasses.

`MasterConfig` holds the keys every station has (rates, eq. 5's scales, the force display,
passivity); the chosen device's own keys (`haply_url`, `arm_dh`, `script`, …) are its
options class's (`DeviceOptions`, declared beside the backend and registered under its name
in `backends.py`). Users write both in one `[master]` table: `MasterConfig.from_mapping`
parses the common keys and hands the rest to the chosen device's options class.

Every value is checked in `__post_init__`; a bad one raises `ConfigError("master.<key>", …)`
so a misspelt or out-of-range setting stops the service before it commands anything.
`option_error`, `number`, `positive`, `string` and `check_buttons` are those checks, for
the options classes too.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any, Literal, cast, get_args

import numpy as np

from services.bus.config import section
from services.bus.errors import ConfigError
from services.control.master.backends import DEVICES, options_class
from services.control.master.device import DeviceOptions
from services.geometry import is_rotation

Frame = Literal["world", "tool"]
FRAMES: tuple[str, ...] = get_args(Frame)

IDENTITY9: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)

_ID_FORBIDDEN = set("/*$?#@ ")
_MAX_NAME = 128
"""Names on the wire (`master`, `device`) are at most 128 characters."""
MAX_BUTTON = 64
"""Button bits are 0 … 63 (`HandReading.buttons`)."""
MAX_RAMP_S = 10.0
MIN_STALE_MS, MAX_STALE_MS = 10.0, 5000.0
DAMPING_MARGIN = 0.5
"""`contact_damping_ns_m` may be at most this fraction of 2·m·rate (the device's moving mass
`passivity_device_mass_kg` × the loop's `rate_hz`): a damper sampled at the loop's rate on
a velocity one tick old is itself unstable past 2·m/T, and the margin leaves room for the
velocity filter's lag and a device lighter than set."""
"""How long a wrist force may be held without a new one: from a few samples to a lease."""
_POSITIVE_KEYS = ("max_force_n", "max_torque_nm")


def option_error(key: str, message: str) -> ConfigError:
    """The error of the `[master]` key `key`."""
    return ConfigError(f"master.{key}", message)


def number(key: str, value: object) -> float:
    """`value` as a float when it is a finite number (not a bool), else the key's error."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise option_error(key, f"must be a number, got {type(value).__name__}")
    if not math.isfinite(value):
        raise option_error(key, "must be finite")
    return float(value)


def positive(options: object, *keys: str) -> None:
    """Each of `keys` of `options` is a number > 0."""
    for key in keys:
        if number(key, getattr(options, key)) <= 0.0:
            raise option_error(key, "must be > 0")


def string(options: object, *keys: str) -> None:
    """Each of `keys` of `options` is a string."""
    for key in keys:
        if not isinstance(getattr(options, key), str):
            raise option_error(key, "must be a string")


def check_buttons(clutch_button: object, grip_button: object) -> None:
    """`clutch_button` and `grip_button` are two different button bits."""
    for key, value in (("clutch_button", clutch_button), ("grip_button", grip_button)):
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < MAX_BUTTON:
            raise option_error(key, f"must be a button bit number 0 … {MAX_BUTTON - 1}")
    if clutch_button == grip_button:
        raise option_error("grip_button", "must differ from clutch_button")


MIN_DEVICE_MASS_KG, MAX_DEVICE_MASS_KG = 0.01, 20.0
"""A haptic device's moving mass at the hand: from a pen-sized stylus to a large arm."""
MIN_DEVICE_INERTIA_KG_M2, MAX_DEVICE_INERTIA_KG_M2 = 1e-5, 1.0
"""Its rotational inertia at the hand: from a stylus's roll to a large arm's wrist."""
DEVICE_INERTIA_KG_M2 = 0.002
"""The default rotational inertia at the hand (kg·m²): a 0.5 kg handle's 6 cm radius of
gyration."""


@dataclass(frozen=True, slots=True)
class MasterConfig:
    """Settings of one master station: the keys every device shares, and the device's own.

    master_id: the master's id on the bus (`alive/master/<id>`, `OperatorCommand.master`).
    device: which backend drives the hand pose (a name of `backends.DEVICES`).
    options: that backend's own keys (its `DeviceOptions`, e.g. `HaplyOptions`); by
        default its defaults.
    rate_hz: command rate, 1–1000 Hz (the contract asks ≥ 50 Hz on `robot/cmd`).
    scale_t, scale_r: eq. 5 motion scales for translation and rotation, 0 < s ≤ 1.
    frame: `world` or `tool` (PROTOCOL §2).
    alignment: A, the master→slave axis alignment, 9 floats row-major, a rotation.
    force_scale: operator force per slave force (N/N and N·m/N·m), ≥ 0.
    max_force_n, max_torque_nm: saturation of the displayed wrench (direction kept).
    engage_on_start: engage at the first tick (True) or only after the operator has
        pressed and released the master-shift (False). None: the device's
        (`DeviceOptions.engages_on_start`: True for `scripted` and `virtual` masters,
        False for devices an operator holds).
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
    reengage: after the decision held this master's engagement for a gap in its command
        stream (its 100 ms watchdog, on a loaded host), start a new engagement where the
        hand is (no jump) while the device still asks to move; false: wait for the operator.
    force_ramp_s: the displayed wrench ramps from zero to full over this time after each
        engagement (0 = at once); it is zero whenever the master is not engaged.
    force_stale_ms: no wrist force *received* for this long and nothing is displayed (the
        last one is held until then: a lost packet or a TCP retransmission is bridged, a
        stream that stopped is not). Counted on this host's clock, never from the sample's
        robot-host stamp. 100 ms suits a LAN; over a lossy TCP link of long delay, longer.
    contact_damping_ns_m: a viscous damper (N·s/m) on the hand's motion, added to the
        displayed force while a contact force is shown (its gain ramps in with that force
        over `feedback.CONTACT_DAMPING_FULL_N`; none in free space). A stiff contact shown
        to a softly held device bounces unless the loop damps at least about the contact's
        stiffness × the loop's delay (Colgate's bound: docs/master.md, "Contact damping").
        0 (default): off. At most DAMPING_MARGIN × 2 × passivity_device_mass_kg × rate_hz.
    contact_tangential_gain: in contact, the part of the displayed force across the
        contact's normal (its friction, mostly) is shown × this, 0 … 1; the part along the
        normal (the press) always in full. The normal is the mean of the wrist force's directions in
        the world frame over the contact's first `feedback.NORMAL_WINDOW_S`
        (`feedback.ContactNormal`). Applied before a passivity port, which observes what the
        hand is shown. 1 (default): the force as measured. Over a delayed link the hand,
        yielding sideways to the friction it is shown a round trip late, drags the tool
        across the surface and TDPA's slave port pays that friction work: at 0 the link
        bench's press was calm at 50 and 200 ms where with friction shown it shook or was
        lost, but lighter at 0 ms (docs/passivity.md, "Friction hidden from the hand").
    """

    master_id: str = "master"
    device: str = "virtual"
    # Never None once built: __post_init__ puts the device's defaults there.
    options: DeviceOptions = field(default=cast(DeviceOptions, None))
    rate_hz: float = 100.0
    scale_t: float = 1.0
    scale_r: float = 1.0
    frame: Frame = "world"
    alignment: tuple[float, ...] = IDENTITY9
    force_scale: float = 1.0
    max_force_n: float = 10.0
    max_torque_nm: float = 1.0
    engage_on_start: bool | None = None
    force_ramp_s: float = 0.5
    reengage: bool = True
    force_stale_ms: float = 100.0
    passivity: bool = False
    passivity_device_mass_kg: float = 0.5
    passivity_moments: bool = False
    passivity_device_inertia_kg_m2: float = DEVICE_INERTIA_KG_M2
    contact_damping_ns_m: float = 0.0
    contact_tangential_gain: float = 1.0

    def __post_init__(self) -> None:
        if not isinstance(self.master_id, str) or not self.master_id:
            raise option_error("master_id", "must be a non-empty string")
        if len(self.master_id) > _MAX_NAME:
            raise option_error("master_id", f"must be at most {_MAX_NAME} characters")
        if _ID_FORBIDDEN & set(self.master_id):
            raise option_error(
                "master_id", "must not contain '/', '*', '$', '?', '#', '@' or spaces"
            )
        self._check_options()
        if not 1.0 <= number("rate_hz", self.rate_hz) <= 1000.0:
            raise option_error("rate_hz", "must be within 1 … 1000 Hz")
        for key in ("scale_t", "scale_r"):
            if not 0.0 < number(key, getattr(self, key)) <= 1.0:
                raise option_error(key, "must satisfy 0 < s ≤ 1")
        if self.frame not in FRAMES:
            raise option_error("frame", "must be 'world' or 'tool'")
        self._check_alignment()
        if number("force_scale", self.force_scale) < 0.0:
            raise option_error("force_scale", "must be ≥ 0")
        positive(self, *_POSITIVE_KEYS)
        for key in ("passivity", "passivity_moments", "reengage"):
            if not isinstance(getattr(self, key), bool):
                raise option_error(key, "must be true or false")
        mass = number("passivity_device_mass_kg", self.passivity_device_mass_kg)
        if not MIN_DEVICE_MASS_KG <= mass <= MAX_DEVICE_MASS_KG:
            raise option_error(
                "passivity_device_mass_kg",
                f"must be within {MIN_DEVICE_MASS_KG:g} … {MAX_DEVICE_MASS_KG:g} kg",
            )
        inertia = number("passivity_device_inertia_kg_m2", self.passivity_device_inertia_kg_m2)
        if not MIN_DEVICE_INERTIA_KG_M2 <= inertia <= MAX_DEVICE_INERTIA_KG_M2:
            raise option_error(
                "passivity_device_inertia_kg_m2",
                f"must be within {MIN_DEVICE_INERTIA_KG_M2:g} … {MAX_DEVICE_INERTIA_KG_M2:g} kg·m²",
            )
        if not 0.0 <= number("force_ramp_s", self.force_ramp_s) <= MAX_RAMP_S:
            raise option_error("force_ramp_s", f"must be within 0 … {MAX_RAMP_S:g} s")
        if not MIN_STALE_MS <= number("force_stale_ms", self.force_stale_ms) <= MAX_STALE_MS:
            raise option_error(
                "force_stale_ms", f"must be within {MIN_STALE_MS:g} … {MAX_STALE_MS:g} ms"
            )
        self._check_damping(mass)
        if not 0.0 <= number("contact_tangential_gain", self.contact_tangential_gain) <= 1.0:
            raise option_error("contact_tangential_gain", "must be within 0 … 1")
        if self.engage_on_start is None:
            object.__setattr__(self, "engage_on_start", type(self.options).engages_on_start)
        elif not isinstance(self.engage_on_start, bool):
            raise option_error("engage_on_start", "must be true or false")

    def _check_damping(self, mass_kg: float) -> None:
        """`contact_damping_ns_m` is ≥ 0 and within the sampled damper's stability bound."""
        b = number("contact_damping_ns_m", self.contact_damping_ns_m)
        b_max = DAMPING_MARGIN * 2.0 * mass_kg * self.rate_hz
        if not 0.0 <= b <= b_max:
            raise option_error(
                "contact_damping_ns_m",
                f"must be within 0 … {b_max:g} N·s/m ({DAMPING_MARGIN:g} × 2 × "
                "passivity_device_mass_kg × rate_hz: a damper sampled at the loop's rate is "
                "unstable beyond 2·m·rate)",
            )

    def _check_options(self) -> None:
        """`device` names a backend and `options` are that backend's (its defaults if none)."""
        if not isinstance(self.device, str):
            raise option_error("device", "must be a string")
        kind = options_class(self.device)
        if self.options is None:
            object.__setattr__(self, "options", kind())
        elif type(self.options) is not kind:
            raise option_error(
                "device",
                f"{self.device!r} takes {kind.__name__}, not {type(self.options).__name__}",
            )

    def _check_alignment(self) -> None:
        values = self.alignment
        if not isinstance(values, tuple | list) or len(values) != 9:
            raise option_error("alignment", "must be 9 numbers (a 3×3 rotation, row-major)")
        floats = tuple(number("alignment", v) for v in values)
        if not is_rotation(np.array(floats).reshape(3, 3)):
            raise option_error("alignment", "must be a rotation (RᵀR = I within 1e-6, det R = +1)")
        object.__setattr__(self, "alignment", floats)

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
        naming `master.<key>`.

        The common keys are this class's; the rest go to the chosen device's options class.
        A key of another device (say `haply_url` with `device = "spacemouse"`) is checked by
        the first device in `backends.DEVICES` that has it, and then unused.
        """
        rest = dict(values)
        common = {k: rest.pop(k) for k in list(rest) if k in _COMMON_KEYS}
        config = section(cls, common, "master")
        chosen = type(config.options)
        own = {k: rest.pop(k) for k in list(rest) if k in _keys(chosen)}
        for name in DEVICES.names:
            if not rest:
                break
            other = options_class(name)
            theirs = {k: rest.pop(k) for k in list(rest) if k in _keys(other)}
            if theirs:
                section(other, theirs, "master")
        if rest:
            known = sorted(_COMMON_KEYS.union(*(_keys(options_class(n)) for n in DEVICES.names)))
            key = next(iter(rest))
            raise option_error(key, f"unknown key (known: {', '.join(known)})")
        return replace(config, options=section(chosen, own, "master"))


def _keys(dataclass_type: type) -> frozenset[str]:
    return frozenset(f.name for f in fields(dataclass_type))


_COMMON_KEYS = _keys(MasterConfig) - {"options"}
"""The keys of `[master]` every device shares (`options` is not one: it is the rest)."""
