"""franky-sim with what it does not simulate, for the tests: reflexes and a wrench.

`python tests/control/arm/franka/fault_sim.py --hostname 127.x.y.z` runs franky-sim's MuJoCo
FR3 exactly as `franky-sim --simulator mujoco` does (its own SimulationServer, robot server
and gripper server, 1 kHz of its clock), plus lines on stdin:

    reflex joint_reflex [more flags]   the robot aborts the running motion as a reflex does:
                                       libfranka's Move answer kReflexAborted, robot mode
                                       Reflex and the flags in the state until
                                       automaticErrorRecovery; a Move meanwhile is refused
    wrench fx fy fz tx ty tz           O_F_ext_hat_K (N, N·m, base frame) from now on

franky-sim reports neither (its O_F_ext_hat_K is zero, it never aborts a motion): these are
what libfranka sees from a real robot in the same places of its protocol (libfranka
robot_impl.cpp `throwOnMotionError`, robot_state.cpp).
"""

from __future__ import annotations

import argparse
import os
import select

from franky_sim.franka_robot_protocol import (
    AutomaticErrorRecoveryStatus,
    BaseCommand,
    MoveStatus,
    RobotCommand,
    RobotMode,
)
from franky_sim.franka_robot_server import FrankaRobotServer
from franky_sim.mujoco_simulator import MujocoSimulator
from franky_sim.simulation_server import SimulationServer

from services.control.arm.franka.errors import ERROR_FLAGS


class FaultyRobotServer(FrankaRobotServer):
    reflex: tuple[bool, ...] | None = None
    wrench: tuple[float, ...] | None = None

    def __init__(self, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
        super().__init__(*args, **kwargs)
        server = self

        class Recovery(BaseCommand):
            command_type = RobotCommand.kAutomaticErrorRecovery

            @classmethod
            def from_bytes(cls, data, command_id, client_socket):  # type: ignore[no-untyped-def]
                return cls(command_id, client_socket)

            def handle(self, _server) -> None:  # type: ignore[no-untyped-def]
                server.reflex = None
                self.reply(AutomaticErrorRecoveryStatus.kSuccess)

        self._FrankaServer__command_class_map[RobotCommand.kAutomaticErrorRecovery] = Recovery

    def start_motion(self, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
        if self.reflex is not None:
            raise RuntimeError("in reflex: recover first")
        super().start_motion(*args, **kwargs)

    def inject_reflex(self, names: list[str]) -> None:
        self.reflex = tuple(n in names for n in ERROR_FLAGS)
        motion = self.current_motion_id
        self.stop_motion(send_preemption_signal=False)
        if motion:
            BaseCommand.send_response(
                self._tcp_socket, RobotCommand.kMove, motion, MoveStatus.kReflexAborted
            )
            self.reset_current_motion_id()

    @property
    def robot_state(self):  # type: ignore[no-untyped-def]
        st = super().robot_state
        if self.reflex is not None:
            st = st.replace(
                robot_mode=RobotMode.kReflex, errors=self.reflex, reflex_reason=self.reflex
            )
        if self.wrench is not None:
            st = st.replace(O_F_ext_hat_K=self.wrench)
        return st


class FaultySimulationServer(SimulationServer):
    def init(self) -> None:
        for robot in self.sim.robots:
            rs = FaultyRobotServer(robot, self._remaining_hostname_candidates)
            rs.init()
            self.robot_servers.append(rs)
        self.sim.start()


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--hostname", required=True)
    args = p.parse_args()
    with MujocoSimulator(enable_visualization=False) as sim:
        robot = sim.add_robot()
        with FaultySimulationServer(sim, hostname_candidates=[args.hostname]) as server:
            print(
                f"Connect to the server using '{robot.hostname}' as the robot IP address",
                flush=True,
            )
            rs = server.robot_servers[0]
            assert isinstance(rs, FaultyRobotServer)
            buf = b""
            while True:
                if select.select([0], [], [], 0)[0]:
                    chunk = os.read(0, 4096)
                    if not chunk:
                        return
                    buf += chunk
                    *lines, buf = buf.split(b"\n")
                    for line in lines:
                        words = line.decode().split()
                        if words and words[0] == "reflex":
                            rs.inject_reflex(words[1:])
                        elif words and words[0] == "wrench":
                            rs.wrench = tuple(float(x) for x in words[1:7])
                server.run_once()


if __name__ == "__main__":
    main()
