"""The console's settings: the `[console]` table of a deployment TOML, read into a frozen
dataclass (`services.bus.config.section`), so a misspelt key fails at start-up."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from services.bus.errors import ConfigError
from services.geometry import V3

_ID_FORBIDDEN = set("/*$?#@ ")
_POSITIVE = (
    "gui_rate_hz",
    "video_fps",
    "plot_window_s",
    "force_rate_hz",
    "status_period_s",
    "force_arrow_m_per_n",
    "gizmo_scale_m",
    "rpc_timeout_s",
    "wait_timeout_s",
)


@dataclass(frozen=True, slots=True)
class ConsoleConfig:
    """Settings of the web console (units in the names; world frame = the arm's base frame).

    host, port: where the page is served (`--host`, `--port`; port 0 = any free port).
    master: start an in-process master with a virtual device (`--master`, default on), so
      the gizmo in the 3D scene teleoperates the arm with no hardware.
    master_id: the master the gizmo drives (`robot/master/<id>/rpc/set_hand`): the
      in-process one, or one started elsewhere with `telerobot master --device virtual`.
    gui_rate_hz: the one GUI thread's rate (the arm, frames, force arrow), 1 … 60 Hz.
    video_fps: the rate at which stereo frames are pushed to the browser (≤ 30);
      video_max_width_px: frames wider than this are decimated before sending;
      video_panel_width_px: the video window's initial width (the image fills it, keeping
      its aspect; the operator can resize it).
    plot_window_s, plot_points: the force/moment plots show the last `plot_window_s`
      seconds, decimated to at most `plot_points` points.
    force_rate_hz: the rate at which Zenoh hands the console robot/force (its session's
      `downsampling`, 1 … 1000): the plots and the arrow need no more.
    events: how many events the log keeps (newest first).
    status_period_s: how often the decision server's and the master's status are polled.
    force_arrow_m_per_n: length of the force arrow per newton (m/N).
    gizmo_scale_m: size of the virtual master's gizmo (m).
    rpc_timeout_s: timeout of a button's call; wait_timeout_s: of a call that waits for a
      motion (`home`).
    shadows: the lights cast shadows (off: cheaper for browsers without a GPU).
    camera_position_m, camera_look_at_m: the initial view (world, m).
    """

    host: str = "127.0.0.1"
    port: int = 8080
    master: bool = True
    master_id: str = "console"
    gui_rate_hz: float = 25.0
    video_fps: float = 12.0
    video_max_width_px: int = 640
    video_panel_width_px: int = 560
    plot_window_s: float = 5.0
    plot_points: int = 400
    force_rate_hz: float = 100.0
    events: int = 50
    status_period_s: float = 0.5
    force_arrow_m_per_n: float = 0.01
    gizmo_scale_m: float = 0.4
    rpc_timeout_s: float = 3.0
    wait_timeout_s: float = 60.0
    shadows: bool = True
    camera_position_m: V3 = (1.35, -0.95, 1.1)
    camera_look_at_m: V3 = (0.45, 0.0, 0.55)

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, float) and not math.isfinite(v):
                raise _err(f.name, "must be finite")
        for key in _POSITIVE:
            if not getattr(self, key) > 0:
                raise _err(key, f"must be > 0, got {getattr(self, key)}")
        if not self.host:
            raise _err("host", "must not be empty")
        if not 0 <= self.port <= 65535:
            raise _err("port", f"must be within 0 … 65535, got {self.port}")
        if not self.master_id or len(self.master_id) > 128 or _ID_FORBIDDEN & set(self.master_id):
            raise _err("master_id", "1 … 128 characters, no '/', '*', '$', '?', '#', '@', space")
        if not 1.0 <= self.gui_rate_hz <= 60.0:
            raise _err("gui_rate_hz", "must be within 1 … 60 Hz")
        if self.video_fps > 30.0:
            raise _err("video_fps", "must be ≤ 30 (the browser is not the video path to record)")
        if self.video_max_width_px < 64:
            raise _err("video_max_width_px", "must be ≥ 64 px")
        if not 160 <= self.video_panel_width_px <= 4096:
            raise _err("video_panel_width_px", "must be within 160 … 4096 px")
        if self.force_rate_hz > 1000.0:
            raise _err("force_rate_hz", "must be ≤ 1000 Hz (the force's own rate)")
        if self.plot_points < 10:
            raise _err("plot_points", "must be ≥ 10")
        if not 1 <= self.events <= 1000:
            raise _err("events", "must be within 1 … 1000")
        for key in ("camera_position_m", "camera_look_at_m"):
            v = getattr(self, key)
            if len(v) != 3 or not all(math.isfinite(x) for x in v):
                raise _err(key, "must be 3 finite numbers (m)")

    @property
    def gui_period_s(self) -> float:
        """The GUI thread's period, 1 / gui_rate_hz."""
        return 1.0 / self.gui_rate_hz


def _err(key: str, message: str) -> ConfigError:
    return ConfigError(f"console.{key}", message)
