"""`telerobot ros2`: Telerobot as ROS 2 sees it over rmw_zenoh (docs/ros2.md).

Settings come from the deployment TOML's `[ros2]` table (`--config`); the flags below
override it. Needs no ROS: ROS 2 machines running rmw_zenoh on the same Zenoh network see
the topics, the node and its endpoints.
"""

from __future__ import annotations

import argparse
import sys

from services.bus.config import add_node_args, node_config, service_config
from services.bus.lifecycle import Shutdown, setup_logging
from services.bus.node import Node
from services.ros2.config import Ros2Config
from services.ros2.service import Ros2Service, bridge_node_config


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="telerobot ros2", description=__doc__)
    add_node_args(p)
    p.add_argument(
        "--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: environment, or 0)"
    )
    p.add_argument("--ros-namespace", default=None, help="the ROS node's namespace")
    p.add_argument("--no-video", dest="video", action="store_false", default=None)
    p.add_argument("--verbose", "-v", action="store_true", help="debug logging")
    args = p.parse_args(argv)
    log = setup_logging("ros2", args.verbose)
    rcfg = service_config(
        Ros2Config,
        args,
        "ros2",
        {"domain_id": args.domain_id, "namespace": args.ros_namespace, "video": args.video},
    )
    cfg = bridge_node_config(node_config(args, connect=("tcp/127.0.0.1:7447",)), rcfg)
    stop = Shutdown()
    with Node("ros2", cfg) as node:
        service = Ros2Service(node, rcfg)
        try:
            log.info(
                "ros2 up: domain %d, node %s, joint_states/tf %.0f Hz, wrench %.0f Hz",
                service.domain_id,
                service.ros.fqn(rcfg.node_name),
                rcfg.state_rate_hz,
                rcfg.wrench_rate_hz,
            )
            stop.wait()
        finally:
            service.close()
    log.info("ros2 stopped")
    return 0


if __name__ == "__main__":
    sys.exit(main())
