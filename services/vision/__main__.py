"""`telerobot vision`: the stereo vision service."""

from __future__ import annotations

import argparse
import sys

from services.bus.config import add_node_args, load_deploy, node_config, service_table
from services.bus.lifecycle import Shutdown, setup_logging
from services.bus.node import Node
from services.cli.introspect import LOCAL_ROUTER
from services.vision.config import VisionConfig


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
    with Node("vision", node_config(args, deploy, connect=(LOCAL_ROUTER,))) as node:
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
