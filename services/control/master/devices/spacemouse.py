"""3Dconnexion SpaceMouse family through hidapi (`import hid`, the `hidapi` package).

The device reports six axis deflections as signed 16-bit little-endian integers, about
±350 at full deflection, in the HID frame (x right, y toward the user, z down, rotations
about those axes). Two report layouts exist:

- older models: report 1 = translation (x, y, z), report 2 = rotation (rx, ry, rz), each
  `id + 3 × int16` (7 bytes);
- newer models: one report 1 = `id + 6 × int16` (13 bytes), translation then rotation.

Buttons come in report 3 as a little-endian bitmask after the id byte (bit 0 = left or
menu button, bit 1 = right or fit button). Layouts and product ids follow PySpaceMouse's
device table and Blender's NDOF manager; decoding is a pure function of the report bytes
driven by `AxisSpec` tables. We output the master frame (x right, y away from the operator,
z up): y, z, ry and rz change sign (a proper rotation of the HID frame by π about x).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.control.master.config import (
    check_buttons,
    number,
    option_error,
    positive,
    string,
)
from services.control.master.device import (
    DeviceLost,
    DeviceNotFound,
    DeviceOptions,
    HandReading,
    MasterDevice,
)
from services.control.master.jog import HandIntegrator, RateScale, apply_deadband

if TYPE_CHECKING:
    from services.control.master.config import MasterConfig

AXIS_NAMES: tuple[str, ...] = ("tx", "ty", "tz", "rx", "ry", "rz")
FULL_SCALE_COUNTS = 350.0
"""Counts at full deflection (3Dconnexion devices send about ±350)."""
BUTTON_REPORT_ID = 3
VENDOR_LOGITECH = 0x046D
VENDOR_3DCONNEXION = 0x256F
_MAX_REPORTS_PER_READ = 256
_REPORT_SIZE = 64


@dataclass(frozen=True, slots=True)
class AxisSpec:
    """Where one axis lives: report id, byte offset of its int16 (little-endian, offset
    counted with the id byte at 0) and the sign that turns HID axes into master axes."""

    report_id: int
    offset: int
    sign: int


@dataclass(frozen=True, slots=True)
class ReportLayout:
    """The six axes (tx, ty, tz, rx, ry, rz), in master-frame order."""

    name: str
    axes: tuple[AxisSpec, AxisSpec, AxisSpec, AxisSpec, AxisSpec, AxisSpec]


TWO_REPORTS = ReportLayout(
    "two-reports",
    (
        AxisSpec(1, 1, +1),
        AxisSpec(1, 3, -1),
        AxisSpec(1, 5, -1),
        AxisSpec(2, 1, +1),
        AxisSpec(2, 3, -1),
        AxisSpec(2, 5, -1),
    ),
)
"""Older models: translation in report 1, rotation in report 2."""

SINGLE_REPORT = ReportLayout(
    "single-report",
    (
        AxisSpec(1, 1, +1),
        AxisSpec(1, 3, -1),
        AxisSpec(1, 5, -1),
        AxisSpec(1, 7, +1),
        AxisSpec(1, 9, -1),
        AxisSpec(1, 11, -1),
    ),
)
"""Newer models: all six axes in one 13-byte report 1."""


@dataclass(frozen=True, slots=True)
class SpaceMouseModel:
    """A known product: USB ids and its report layout."""

    name: str
    vendor_id: int
    product_id: int
    layout: ReportLayout


MODELS: tuple[SpaceMouseModel, ...] = (
    SpaceMouseModel("SpacePilot", VENDOR_LOGITECH, 0xC625, TWO_REPORTS),
    SpaceMouseModel("SpaceNavigator", VENDOR_LOGITECH, 0xC626, TWO_REPORTS),
    SpaceMouseModel("SpaceExplorer", VENDOR_LOGITECH, 0xC627, TWO_REPORTS),
    SpaceMouseModel("SpaceNavigator for Notebooks", VENDOR_LOGITECH, 0xC628, TWO_REPORTS),
    SpaceMouseModel("SpacePilot Pro", VENDOR_LOGITECH, 0xC629, TWO_REPORTS),
    SpaceMouseModel("SpaceMouse Pro", VENDOR_LOGITECH, 0xC62B, TWO_REPORTS),
    SpaceMouseModel("SpaceMouse Wireless (cable)", VENDOR_3DCONNEXION, 0xC62E, SINGLE_REPORT),
    SpaceMouseModel("SpaceMouse Wireless (receiver)", VENDOR_3DCONNEXION, 0xC62F, SINGLE_REPORT),
    SpaceMouseModel("SpaceMouse Pro Wireless (cable)", VENDOR_3DCONNEXION, 0xC631, SINGLE_REPORT),
    SpaceMouseModel("SpaceMouse Pro Wireless", VENDOR_3DCONNEXION, 0xC632, SINGLE_REPORT),
    SpaceMouseModel("SpaceMouse Enterprise", VENDOR_3DCONNEXION, 0xC633, SINGLE_REPORT),
    SpaceMouseModel("SpaceMouse Compact", VENDOR_3DCONNEXION, 0xC635, TWO_REPORTS),
    SpaceMouseModel("SpaceMouse Pro Wireless (BT)", VENDOR_3DCONNEXION, 0xC638, SINGLE_REPORT),
    SpaceMouseModel("SpaceMouse Wireless (new)", VENDOR_3DCONNEXION, 0xC63A, SINGLE_REPORT),
    SpaceMouseModel("SpaceMouse (USB)", VENDOR_3DCONNEXION, 0xC641, TWO_REPORTS),
    SpaceMouseModel("Universal Receiver", VENDOR_3DCONNEXION, 0xC652, SINGLE_REPORT),
)


def find_model(vendor_id: int, product_id: int) -> SpaceMouseModel | None:
    """The known model with these ids; an unknown 3Dconnexion product (vendor 0x256f) is
    taken as a newer single-report device; any other unknown id is not a SpaceMouse (0x046d
    is Logitech, whose mice and keyboards must not be picked up)."""
    for model in MODELS:
        if model.vendor_id == vendor_id and model.product_id == product_id:
            return model
    if vendor_id == VENDOR_3DCONNEXION:
        return SpaceMouseModel(
            f"3Dconnexion {product_id:04x}", vendor_id, product_id, SINGLE_REPORT
        )
    return None


@dataclass(frozen=True, slots=True)
class DecodedReport:
    """What one report says: normalised deflections (None = not in this report) and the
    button bitmask (None = not a button report)."""

    axes: tuple[float | None, ...]
    buttons: int | None


def _int16_le(report: bytes, offset: int) -> int:
    return int.from_bytes(report[offset : offset + 2], "little", signed=True)


def decode_report(report: bytes | bytearray | list[int], layout: ReportLayout) -> DecodedReport:
    """Decode one HID input report (id byte first) with `layout`.

    Axis values are `sign · raw / 350`, not clipped (the deadband clips later). Axes whose
    bytes lie beyond the report are left out, so a short or unknown report changes nothing.
    """
    data = bytes(report)
    if not data:
        return DecodedReport((None,) * 6, None)
    report_id = data[0]
    if report_id == BUTTON_REPORT_ID:
        return DecodedReport((None,) * 6, int.from_bytes(data[1:], "little"))
    axes: list[float | None] = []
    for spec in layout.axes:
        if spec.report_id == report_id and spec.offset + 2 <= len(data):
            axes.append(spec.sign * _int16_le(data, spec.offset) / FULL_SCALE_COUNTS)
        else:
            axes.append(None)
    return DecodedReport(tuple(axes), None)


class SpaceMouseState:
    """Latest deflections and buttons, merged report by report (pure, no I/O)."""

    def __init__(self, layout: ReportLayout) -> None:
        self.layout = layout
        self.deflection = np.zeros(6)
        self.buttons = 0

    def feed(self, report: bytes | bytearray | list[int]) -> None:
        """Merge one report. A 13-byte report 1 on a model listed as two-report switches to
        the single-report layout: firmware updates have moved models between layouts."""
        data = bytes(report)
        if self.layout is TWO_REPORTS and len(data) >= 13 and data[0] == 1:
            self.layout = SINGLE_REPORT
        decoded = decode_report(data, self.layout)
        for i, value in enumerate(decoded.axes):
            if value is not None:
                self.deflection[i] = value
        if decoded.buttons is not None:
            self.buttons = decoded.buttons


def _describe(entry: dict[str, Any]) -> str:
    vid = int(entry.get("vendor_id", 0))
    pid = int(entry.get("product_id", 0))
    maker = entry.get("manufacturer_string") or ""
    product = entry.get("product_string") or ""
    return f"{vid:04x}:{pid:04x} {maker} {product}".strip()


@dataclass(frozen=True, slots=True)
class SpaceMouseOptions(DeviceOptions):
    """`device = "spacemouse"`: its `[master]` keys.

    port: the HID path ("" = the first SpaceMouse found).
    deadband: fraction of full deflection read as zero, 0 ≤ d < 1.
    sensitivity: multiplier on the full-deflection speeds, > 0.
    full_speed_m_s, full_rate_rad_s: hand speed at full deflection.
    clutch_button, grip_button: bit numbers of the master-shift and grip-toggle buttons.
    """

    port: str = ""
    deadband: float = 0.05
    sensitivity: float = 1.0
    full_speed_m_s: float = 0.1
    full_rate_rad_s: float = 0.5
    clutch_button: int = 0
    grip_button: int = 1

    def __post_init__(self) -> None:
        string(self, "port")
        positive(self, "sensitivity", "full_speed_m_s", "full_rate_rad_s")
        if not 0.0 <= number("deadband", self.deadband) < 1.0:
            raise option_error("deadband", "must satisfy 0 ≤ d < 1")
        check_buttons(self.clutch_button, self.grip_button)

    def build(self, config: MasterConfig) -> MasterDevice:
        return HidSpaceMouse(
            self.port or None,
            deadband=self.deadband,
            sensitivity=self.sensitivity,
            full_speed_m_s=self.full_speed_m_s,
            full_rate_rad_s=self.full_rate_rad_s,
            clutch_button=self.clutch_button,
            grip_button=self.grip_button,
        )


class HidSpaceMouse:
    """A SpaceMouse as a rate-controlled master (`MasterDevice`).

    Deflection → deadband → × sensitivity × full-deflection speed → hand twist, integrated
    into a hand pose (see `HandIntegrator`). The `clutch_button` held is the master-shift;
    each press of `grip_button` toggles the grip between open (0) and closed (1). While the
    master-shift is held the hand pose does not move, so it stays where the operator left it.
    """

    def __init__(
        self,
        path: bytes | str | None = None,
        *,
        deadband: float = 0.05,
        sensitivity: float = 1.0,
        full_speed_m_s: float = 0.1,
        full_rate_rad_s: float = 0.5,
        clutch_button: int = 0,
        grip_button: int = 1,
        hid_api: Any = None,
    ) -> None:
        """path: the HID path to open (None: the first SpaceMouse found). hid_api: the
        hidapi module, or an object with the same `enumerate()`/`device()` API."""
        if not 0.0 <= deadband < 1.0:
            raise ValueError("deadband must satisfy 0 ≤ d < 1")
        self._path = path.encode() if isinstance(path, str) else path
        self._deadband = deadband
        self._rates = RateScale(full_speed_m_s * sensitivity, full_rate_rad_s * sensitivity)
        self._clutch_mask = 1 << clutch_button
        self._grip_mask = 1 << grip_button
        self._hid_api = hid_api
        self._dev: Any = None
        self._model: SpaceMouseModel | None = None
        self._state = SpaceMouseState(SINGLE_REPORT)
        self._hand = HandIntegrator()
        self._grip = 0.0
        self._prev_buttons = 0

    @property
    def name(self) -> str:
        return f"spacemouse:{self._model.name}" if self._model else "spacemouse"

    @property
    def can_display_force(self) -> bool:
        return False

    @property
    def model(self) -> SpaceMouseModel | None:
        """The model opened, None before open()."""
        return self._model

    def open(self) -> None:
        hid = self._hid_api if self._hid_api is not None else importlib.import_module("hid")
        entries = [dict(e) for e in hid.enumerate()]
        chosen: dict[str, Any] | None = None
        for entry in entries:
            model = find_model(int(entry.get("vendor_id", 0)), int(entry.get("product_id", 0)))
            if model is None or (self._path is not None and entry.get("path") != self._path):
                continue
            # The multi-axis controller collection (usage page 1, usage 8) when the device
            # exposes several; hidapi leaves usage 0 where the platform does not report it.
            if chosen is None or (entry.get("usage_page"), entry.get("usage")) == (1, 8):
                chosen, self._model = entry, model
        if chosen is None or self._model is None:
            wanted = "SpaceMouse" + (f" at {self._path!r}" if self._path is not None else "")
            raise DeviceNotFound(f"no 3Dconnexion {wanted}", [_describe(e) for e in entries])
        dev = hid.device()
        try:
            dev.open_path(chosen["path"])
        except OSError as exc:
            raise DeviceNotFound(
                f"cannot open {_describe(chosen)} ({exc}); check the udev rule for hidraw",
                [_describe(e) for e in entries],
            ) from exc
        dev.set_nonblocking(1)
        self._dev = dev
        self._state = SpaceMouseState(self._model.layout)
        self._hand.reset()

    def _drain(self) -> None:
        for _ in range(_MAX_REPORTS_PER_READ):
            try:
                data = self._dev.read(_REPORT_SIZE, 0)
            except (OSError, ValueError) as exc:
                raise DeviceLost(f"{self.name}: {exc}") from exc
            if not data:
                return
            self._state.feed(data)

    def read(self, dt_s: float) -> HandReading:
        if self._dev is None:
            raise DeviceLost("SpaceMouse is not open")
        self._drain()
        buttons = self._state.buttons
        if buttons & self._grip_mask and not self._prev_buttons & self._grip_mask:
            self._grip = 1.0 - self._grip
        self._prev_buttons = buttons
        clutch = bool(buttons & self._clutch_mask)
        if not clutch:
            v, w = self._rates.twist(apply_deadband(self._state.deflection, self._deadband))
            self._hand.step(v, w, dt_s)
        p, R = self._hand.pose
        return HandReading(p, R, clutch, self._grip, buttons)

    def deflection(self) -> NDArray[np.float64]:
        """The latest raw normalised deflections (tx, ty, tz, rx, ry, rz), master frame."""
        return self._state.deflection.copy()

    def display_force(self, f: ArrayLike, c: ArrayLike) -> None:
        """A SpaceMouse cannot push back: nothing to do."""

    def close(self) -> None:
        if self._dev is not None:
            self._dev.close()
            self._dev = None
