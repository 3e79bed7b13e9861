"""A stand-in for the `hid` module of the hidapi package, serving recorded input reports.

It has the calls `HidSpaceMouse` makes, with hidapi's shapes: `enumerate()` returns dicts
with `path` (bytes), `vendor_id`, `product_id`, `manufacturer_string`, `product_string`,
`usage_page`, `usage`; `device()` returns an object with `open_path`, `set_nonblocking`,
`read(max_length, timeout_ms=0)` (a list of ints, empty when nothing is pending),
`close()`. Reports are queued per path with `push`; `unplug` makes the next read fail as
hidapi does when the device goes away.

A fake of the library, not of a device, so it lives with the tests: pass it to
`HidSpaceMouse(hid_api=…)`, or put it in `sys.modules["hid"]` to reach the backend through
`open_master_device(config)`.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class FakeHidInfo:
    """One enumerated HID interface."""

    path: bytes
    vendor_id: int
    product_id: int
    product_string: str
    manufacturer_string: str = "3Dconnexion"
    usage_page: int = 1
    usage: int = 8

    def as_dict(self) -> dict[str, object]:
        return {
            "path": self.path,
            "vendor_id": self.vendor_id,
            "product_id": self.product_id,
            "serial_number": "",
            "release_number": 0x0430,
            "manufacturer_string": self.manufacturer_string,
            "product_string": self.product_string,
            "usage_page": self.usage_page,
            "usage": self.usage,
            "interface_number": 0,
        }


class FakeHidApi:
    """The fake `hid` module: a set of plugged-in devices and their pending reports."""

    def __init__(self, devices: list[FakeHidInfo] | tuple[FakeHidInfo, ...] = ()) -> None:
        self._lock = threading.Lock()
        self._devices = list(devices)
        self._queues: dict[bytes, deque[bytes]] = {d.path: deque() for d in self._devices}
        self._unplugged: set[bytes] = set()
        self.opened: list[bytes] = []
        self.closed = 0

    def push(self, path: bytes, *reports: bytes) -> None:
        """Queue input reports (id byte first) for the device at `path`."""
        with self._lock:
            self._queues[path].extend(bytes(r) for r in reports)

    def pending(self, path: bytes) -> int:
        with self._lock:
            return len(self._queues[path])

    def unplug(self, path: bytes) -> None:
        with self._lock:
            self._unplugged.add(path)

    def enumerate(self, vendor_id: int = 0, product_id: int = 0) -> list[dict[str, object]]:
        with self._lock:
            return [
                d.as_dict()
                for d in self._devices
                if d.path not in self._unplugged
                and vendor_id in (0, d.vendor_id)
                and product_id in (0, d.product_id)
            ]

    def device(self) -> FakeHidDevice:
        return FakeHidDevice(self)

    def _read(self, path: bytes, max_length: int) -> list[int]:
        with self._lock:
            if path in self._unplugged:
                raise OSError("read error")
            queue = self._queues[path]
            return list(queue.popleft()[:max_length]) if queue else []


class FakeHidDevice:
    """hidapi's `hid.device` over a FakeHidApi."""

    def __init__(self, api: FakeHidApi) -> None:
        self._api = api
        self._path: bytes | None = None
        self.nonblocking = False

    def open_path(self, path: bytes) -> None:
        if path not in self._api._queues or path in self._api._unplugged:
            raise OSError("open failed")
        self._path = path
        self._api.opened.append(path)

    def set_nonblocking(self, value: int) -> int:
        self.nonblocking = bool(value)
        return 0

    def read(self, max_length: int, timeout_ms: int = 0) -> list[int]:
        if self._path is None:
            raise ValueError("not open")
        return self._api._read(self._path, max_length)

    def close(self) -> None:
        if self._path is not None:
            self._path = None
            self._api.closed += 1
