"""The skeleton every fake device shares: a socket on 127.0.0.1 served by one thread.

A fake (a serial force sensor, a Net F/T, a master arm) subclasses `LoopbackServer` and
implements `_session(conn)` for one TCP client (or, over UDP, `_serve()`: loop until
`self._closed` is set, using `self._sock`); it gets the port, the pyserial URL, the accept
loop, start/close and the context manager from here. Loopback only:
a fake never listens on another address.
"""

from __future__ import annotations

import socket
import threading
from types import TracebackType
from typing import Literal, Self


class LoopbackServer:
    """A TCP (listening, one client at a time) or UDP socket on 127.0.0.1:`port` (0 = a free
    one) and the daemon thread that runs `_serve()` once started."""

    def __init__(self, kind: Literal["tcp", "udp"], port: int, thread_name: str) -> None:
        if kind == "tcp":
            self._sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._sock.bind(("127.0.0.1", port))
            self._sock.listen(1)
        else:
            self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._sock.bind(("127.0.0.1", port))
        self._closed = threading.Event()
        self._thread: threading.Thread | None = None
        self._thread_name = thread_name
        self.connections = 0
        """TCP clients accepted so far."""

    @property
    def port(self) -> int:
        return int(self._sock.getsockname()[1])

    @property
    def url(self) -> str:
        """The pyserial URL of a TCP fake (`socket://127.0.0.1:PORT`)."""
        return f"socket://127.0.0.1:{self.port}"

    def start(self) -> Self:
        self._thread = threading.Thread(target=self._serve, name=self._thread_name, daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop serving (waits up to 2 s for the thread) and close the socket."""
        self._closed.set()
        if self._thread is not None:
            self._thread.join(2.0)
        self._sock.close()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(
        self,
        et: type[BaseException] | None,
        ev: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def _serve(self) -> None:
        """TCP: accept one client at a time (TCP_NODELAY) and run `_session` on it until the
        fake is closed. A UDP fake overrides this."""
        self._sock.settimeout(0.05)
        while not self._closed.is_set():
            try:
                conn, _ = self._sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            self.connections += 1
            with conn:
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                self._session(conn)

    def _session(self, conn: socket.socket) -> None:
        raise NotImplementedError
