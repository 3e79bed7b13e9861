"""`telerobot ros2`: Telerobot as ROS 2 sees it over rmw_zenoh (docs/ros2.md).

Settings come from the deployment TOML's `[ros2]` table (`--config`); the flags below
override it. Needs no ROS: ROS 2 machines running rmw_zenoh on the same Zenoh network see
the topics, the node and its endpoints.
"""

from __future__ import annotations

import argparse
import sys

from services.bus.config import section, service_table
from services.bus.lifecycle import ServiceContext, run_service
from services.frontends.ros2.config import Ros2Config
from services.frontends.ros2.service import Ros2Service, bridge_node_config


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: environment, or 0)"
    )
    p.add_argument("--ros-namespace", default=None, help="the ROS node's namespace")
    p.add_argument("--no-video", dest="video", action="store_false", default=None)


def start(ctx: ServiceContext) -> None:
    args = ctx.args
    overrides = {"domain_id": args.domain_id, "namespace": args.ros_namespace, "video": args.video}
    rcfg = section(Ros2Config, service_table(ctx.deploy, "ros2", overrides), "ros2")
    service = Ros2Service(ctx.open(bridge_node_config(ctx.node_config, rcfg)), rcfg)
    ctx.closing(service)
    ctx.log.info(
        "ros2 up: domain %d, node %s, joint_states/tf %.0f Hz, wrench %.0f Hz",
        service.domain_id,
        service.ros.fqn(rcfg.node_name),
        rcfg.state_rate_hz,
        rcfg.wrench_rate_hz,
    )


def main(argv: list[str] | None = None) -> int:
    return run_service("ros2", argv, start, description=__doc__, add_arguments=arguments)


if __name__ == "__main__":
    sys.exit(main())
