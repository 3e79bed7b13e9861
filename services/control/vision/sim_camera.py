"""`SimStereoCamera`: a stereo rig looking at the simulated workcell and the simulated arm."""

from __future__ import annotations

import threading
import time

from numpy.typing import ArrayLike

from services.control.vision.camera import CameraError, StereoPair
from services.control.vision.config import VisionConfig
from services.control.vision.objects import ObjectPose, Spills, objects_of_state, steady
from services.control.vision.render import RobotPose, StereoRenderer
from services.control.vision.rig import StereoRig
from services.world.workcell.messages import WorkcellState, objects_of
from services.world.workcell.scene import Scene, default_scene


class SimStereoCamera:
    """Renders the workcell and the arm from two pinhole cameras (see `StereoRig.look_at`).

    The rig is `config`'s (`rig_position_m`, `rig_target_m`, `baseline_m`, `fov_deg`,
    `width`, `height`). `set_robot` may be called from any thread (a bus callback); `grab`
    renders the latest pose it was given, both eyes from the same pose, so both capture
    times are the same instant: when `grab` took that pose.
    """

    def __init__(
        self,
        config: VisionConfig | None = None,
        scene: Scene | None = None,
        supersample: int = 2,
    ) -> None:
        self.config = config if config is not None else VisionConfig()
        self.rig = StereoRig.from_config(self.config)
        self._scene = scene if scene is not None else default_scene()
        self._supersample = supersample
        self._renderer: StereoRenderer | None = None
        self._robot: RobotPose | None = None
        self._objects: tuple[ObjectPose, ...] | None = None
        self._spills = Spills(self._scene)
        self._lock = threading.Lock()

    @property
    def name(self) -> str:
        return "sim"

    @property
    def scene(self) -> Scene:
        return self._scene

    def open(self) -> None:
        """Ray-cast the static scene for both eyes (a few hundred ms at 640×480)."""
        with self._lock:
            if self._renderer is None:
                self._renderer = self._build(self._scene)

    def close(self) -> None:
        with self._lock:
            self._renderer = None

    def set_robot(
        self,
        link_points: ArrayLike,
        tool_p: ArrayLike,
        tool_R: ArrayLike,
        grip: float | None = None,
    ) -> None:
        """The arm to draw from now on, in world coordinates (m).

        `link_points` (k, 3): the arm's skeleton, base to flange
        (`Kinematics.link_origins(q)`); `tool_p` (3); `tool_R` (3, 3) or 9 floats row-major;
        `grip` 0 open … 1 closed, None for no gripper. Raises ValueError on a bad shape or a
        non-finite value, leaving the previous pose in place.
        """
        self._robot = RobotPose.make(link_points, tool_p, tool_R, grip)

    def clear_robot(self) -> None:
        """Stop drawing the arm (e.g. when its state has gone stale)."""
        self._robot = None

    def set_workcell(self, state: WorkcellState) -> None:
        """Draw the movable objects where `workcell/state` puts them from the next pair on.

        Raises ProtocolError (a malformed object map) or ValueError (a size, position or
        rotation out of bounds), leaving the previous poses in place. Objects are coloured
        by the scene description (`scene`); one it does not know is grey. Spilled liquid
        is drawn as puddles where it fell (`Spills`). Call from one thread at a time (the
        bus delivers one subscription's messages in order).
        """
        views = objects_of(state)
        objects = objects_of_state(self._scene, views)
        self._spills.update(views)
        # a resting object stays where it was drawn (`steady`): not ray-cast again for the
        # solver's micrometres
        self._objects = steady(self._objects, objects + self._spills.objects())

    def set_scene(self, scene: Scene) -> None:
        """Replace the workcell (re-ray-casts the background now if the camera is open)."""
        with self._lock:
            self._scene = scene
            self._spills = Spills(scene)
            if self._renderer is not None:
                self._renderer = self._build(scene)

    def grab(self) -> StereoPair:
        renderer = self._renderer
        if renderer is None:
            raise CameraError("sim camera: grab() before open()")
        robot, objects = self._robot, self._objects
        t_ns = time.time_ns()
        left, right = renderer.render(robot, objects)
        return StereoPair(left, right, t_ns, t_ns, self.rig.intrinsics, self.rig.baseline_m)

    def keep_alive(self) -> bool:
        """Nothing to keep alive: a simulator renders nothing while nobody watches."""
        if self._renderer is None:
            raise CameraError("sim camera: keep_alive() before open()")
        return False

    def _build(self, scene: Scene) -> StereoRenderer:
        return StereoRenderer(scene, self.rig.left, self.rig.right, self._supersample)
