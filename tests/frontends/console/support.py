"""Helpers of the console tests: waiting on a condition, a ready robot state, and a browser
as viser sees one, without a browser.

viser counts a client as connected once its websocket (subprotocol `viser-v<version>`) has
sent the first camera message, and as gone when the socket closes. `FakeBrowser` does just
that and reads whatever the server sends, as a page would, so the server's queue never
backs up; with `decode=True` it unpacks viser's wire format (a zstd-compressed msgpack batch
of messages) and keeps, per scene node and per GUI element, the newest value of every
property the page was sent (a removed node is forgotten, its children with it).
"""

from __future__ import annotations

import threading
import time
from types import TracebackType
from typing import Any

import msgpack
import viser
import zstandard
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect

from services.bus.messages import IDENTITY_R, RobotState
from tests.conftest import wait_until

__all__ = ["FakeBrowser", "gui_uuid", "ready_state", "wait_until"]


def ready_state(
    seq: int, tool_p: tuple[float, float, float], q: tuple[float, ...] = (0.0,) * 6
) -> RobotState:
    """A `ready` robot/state at joints `q` with the tool (and the flange) at `tool_p`, axes
    as the world's (no arm is described: the console draws none)."""
    return RobotState(
        seq=seq,
        t_ns=time.time_ns(),
        status="ready",
        q=q,
        tool_p=tool_p,
        tool_R=IDENTITY_R,
        flange_p=tool_p,
        flange_R=IDENTITY_R,
        engage=0,
        cmd_seq=0,
    )


class FakeBrowser:
    """A page connected to the console at `port` (127.0.0.1) until `close()`."""

    def __init__(self, port: int, decode: bool = False) -> None:
        self.received = 0
        self._decode = decode
        self._lock = threading.Lock()
        self._nodes: dict[str, dict[str, Any]] = {}
        self._gui: dict[str, dict[str, Any]] = {}
        self._ws: ClientConnection = connect(
            f"ws://127.0.0.1:{port}",
            subprotocols=[f"viser-v{viser.__version__}"],  # type: ignore[list-item]
            max_size=None,
        )
        self._ws.send(
            msgpack.packb(
                {
                    "type": "ViewerCameraMessage",
                    "wxyz": [1.0, 0.0, 0.0, 0.0],
                    "position": [2.0, -1.5, 1.5],
                    "fov": 1.0,
                    "near": 0.01,
                    "far": 100.0,
                    "image_height": 480,
                    "image_width": 640,
                    "look_at": [0.45, 0.0, 0.55],
                    "up_direction": [0.0, 0.0, 1.0],
                }
            )
        )
        self._reader = threading.Thread(target=self._read, name="fake-browser", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        try:
            for raw in self._ws:
                if self._decode and isinstance(raw, bytes):
                    self._store(raw)
                self.received += 1
        except ConnectionClosed:
            pass

    def _store(self, raw: bytes) -> None:
        size = int.from_bytes(raw[0:8], "little")
        n = int.from_bytes(raw[8:16], "little")
        inner = zstandard.ZstdDecompressor().decompress(raw[16 : 16 + n], max_output_size=size)
        with self._lock:
            for m in msgpack.unpackb(inner, raw=False, strict_map_key=False)["messages"]:
                kind = m.get("type", "")
                if kind.endswith("Message") and "props" in m and "name" in m:
                    self._nodes[m["name"]] = {
                        "type": kind,
                        **m["props"],
                        "position": (0.0, 0.0, 0.0),
                        "wxyz": (1.0, 0.0, 0.0, 0.0),
                    }
                elif kind == "RemoveSceneNodeMessage":
                    gone = m["name"]
                    for name in [n for n in self._nodes if n == gone or n.startswith(gone + "/")]:
                        del self._nodes[name]
                elif kind == "SetPositionMessage":
                    self._nodes.setdefault(m["name"], {})["position"] = tuple(m["position"])
                elif kind == "SetOrientationMessage":
                    self._nodes.setdefault(m["name"], {})["wxyz"] = tuple(m["wxyz"])
                elif kind == "SetSceneNodeVisibilityMessage":
                    self._nodes.setdefault(m["name"], {})["visible"] = m["visible"]
                elif kind == "SceneNodeUpdateMessage":
                    self._nodes.setdefault(m["name"], {}).update(m["updates"])
                elif kind == "GuiUpdateMessage":
                    self._gui.setdefault(m["uuid"], {}).update(m["updates"])
                elif kind.startswith("Gui") and "uuid" in m and "props" in m:
                    self._gui.setdefault(m["uuid"], {}).update(m["props"])

    def node(self, name: str) -> dict[str, Any]:
        """What the page was last told of scene node `name` (decode=True)."""
        with self._lock:
            return dict(self._nodes.get(name, {}))

    def nodes(self, prefix: str) -> dict[str, dict[str, Any]]:
        """Every scene node the page holds whose name starts with `prefix` (decode=True)."""
        with self._lock:
            return {k: dict(v) for k, v in self._nodes.items() if k.startswith(prefix)}

    def gui(self, uuid: str) -> dict[str, Any]:
        """What the page was last told of GUI element `uuid` (decode=True)."""
        with self._lock:
            return dict(self._gui.get(uuid, {}))

    def close(self) -> None:
        self._ws.close()
        self._reader.join(timeout=5.0)

    def __enter__(self) -> FakeBrowser:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def gui_uuid(browser: FakeBrowser, label: str, timeout_s: float = 10.0) -> str:
    """The uuid of the GUI element the page was first sent with `label`, or (for an HTML
    element, which has none) whose content holds `label`."""
    found: list[str] = []

    def match(props: dict[str, Any]) -> bool:
        content = props.get("content")
        return props.get("label") == label or (isinstance(content, str) and label in content)

    def look() -> bool:
        with browser._lock:
            found.extend(u for u, props in browser._gui.items() if match(props))
        return bool(found)

    if not wait_until(look, timeout_s):
        raise AssertionError(f"no GUI element {label!r} reached the page")
    return found[0]
