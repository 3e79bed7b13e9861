"""Closing a pyserial port for good, whatever state its far end is in."""

from __future__ import annotations

import contextlib
from typing import Any


def close_port(ser: Any) -> None:
    """Close `ser` (a pyserial port) and its socket, never raising.

    pyserial's `socket://` handler (our fakes, serial-over-TCP adapters) skips closing its
    socket when `shutdown()` fails on a connection the far end already dropped (a pulled
    cable, a USB adapter gone): every reconnect attempt then leaks a file descriptor. A
    vanished port may also fail to close at all; it is gone either way.
    """
    sock = getattr(ser, "_socket", None)
    with contextlib.suppress(OSError):
        ser.close()
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.close()
