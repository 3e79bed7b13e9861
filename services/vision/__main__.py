"""`telerobot vision`: the stereo vision service."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

from services.bus import keys
from services.bus.config import (
    NodeConfig,
    add_node_args,
    load_deploy,
    node_config,
    service_table,
)
from services.bus.lifecycle import Shutdown, setup_logging
from services.bus.node import Node
from services.cli.introspect import LOCAL_ROUTER
from services.vision.config import VisionConfig


def vision_node_config(cfg: NodeConfig, config: VisionConfig) -> NodeConfig:
    """The vision session: the simulator draws the arm from `robot/state` at most twice a
    frame, so Zenoh hands it no more than that (the puma publishes at ≥ 100 Hz)."""
    if config.camera != "sim":
        return cfg
    return replace(cfg, downsampling=(*cfg.downsampling, (keys.STATE.key, 2.0 * config.fps)))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="telerobot vision", description=__doc__)
    p.add_argument("--camera", choices=["sim", "opencv"], default=None)
    p.add_argument("--size", default=None, help="per-eye size, e.g. 640x480")
    p.add_argument("--fps", type=float, default=None)
    p.add_argument("--encoding", choices=["jpeg", "bgr8"], default=None)
    p.add_argument("--quality", type=int, default=None, help="JPEG quality 1…100")
    p.add_argument("--device", action="append", default=None, help="OpenCV device (repeat for 2)")
    p.add_argument("--file", action="append", default=None, help="video file (repeat for 2)")
    add_node_args(p)
    args = p.parse_args(argv)
    log = setup_logging("vision")
    deploy = load_deploy(args.config)
    overrides = {
        "camera": args.camera,
        "size": args.size,
        "fps": args.fps,
        "encoding": args.encoding,
        "jpeg_quality": args.quality,
        "devices": [int(d) if d.isdigit() else d for d in args.device or []] or None,
        "files": args.file,
    }
    table = service_table(deploy, "vision", overrides)
    config = VisionConfig.from_mapping(table)
    from services.vision.service import VisionService

    stop = Shutdown()
    node_cfg = vision_node_config(node_config(args, deploy, connect=(LOCAL_ROUTER,)), config)
    with Node("vision", node_cfg) as node:
        svc = VisionService(node, config)
        log.info(
            "streaming %dx%d at %.0f fps (%s)",
            config.width,
            config.height,
            config.fps,
            config.camera,
        )
        try:
            stop.wait()
        finally:
            svc.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
