"""`telerobot vision`: the stereo vision service."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

from services.bus import keys
from services.bus.config import NodeConfig, service_table
from services.bus.lifecycle import ServiceContext, run_service
from services.control.vision.config import VisionConfig
from services.world.workcell.scene_file import deploy_scene


def vision_node_config(cfg: NodeConfig, config: VisionConfig) -> NodeConfig:
    """The vision session: the simulator draws the arm from `robot/state` at most twice a
    frame, so Zenoh hands it no more than that (the arm publishes at ≥ 100 Hz)."""
    if config.camera != "sim":
        return cfg
    return replace(cfg, downsampling=(*cfg.downsampling, (keys.STATE.key, 2.0 * config.fps)))


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--camera", choices=["sim", "opencv"], default=None)
    p.add_argument("--size", default=None, help="per-eye size, e.g. 640x480")
    p.add_argument("--fps", type=float, default=None)
    p.add_argument("--encoding", choices=["jpeg", "bgr8"], default=None)
    p.add_argument("--quality", type=int, default=None, help="JPEG quality 1…100")
    p.add_argument("--device", action="append", default=None, help="OpenCV device (repeat for 2)")
    p.add_argument("--file", action="append", default=None, help="video file (repeat for 2)")


def start(ctx: ServiceContext) -> None:
    args = ctx.args
    overrides = {
        "camera": args.camera,
        "size": args.size,
        "fps": args.fps,
        "encoding": args.encoding,
        "jpeg_quality": args.quality,
        "devices": [int(d) if d.isdigit() else d for d in args.device or []] or None,
        "files": args.file,
    }
    config = VisionConfig.from_mapping(service_table(ctx.deploy, "vision", overrides))
    # [scene] file: what the simulated cameras look at, the workcell's own (docs/sim.md)
    scene = deploy_scene(ctx.deploy) if config.camera == "sim" else None
    from services.control.vision.service import VisionService

    node = ctx.open(vision_node_config(ctx.node_config, config))
    ctx.closing(VisionService(node, config, scene=scene))
    ctx.log.info(
        "streaming %dx%d at %.0f fps (%s)", config.width, config.height, config.fps, config.camera
    )


def main(argv: list[str] | None = None) -> int:
    return run_service("vision", argv, start, description=__doc__, add_arguments=arguments)


if __name__ == "__main__":
    sys.exit(main())
