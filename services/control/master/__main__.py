"""`telerobot master`: the master station (a SpaceMouse, a serial master arm, a Haply
Inverse3 with its VerseGrip, the keyboard, a scripted operator or the web console's virtual
master)."""

from __future__ import annotations

import argparse
import sys

from services.bus.config import service_table
from services.bus.lifecycle import CONFIG_EXIT, ServiceContext, run_service
from services.control.master.config import MasterConfig
from services.control.master.device import DeviceNotFound

#: command-line names → MasterConfig.device
DEVICES = {
    "spacemouse": "spacemouse",
    "serial": "serial_arm",
    "serial_arm": "serial_arm",
    "keyboard": "keyboard",
    "script": "scripted",
    "scripted": "scripted",
    "virtual": "virtual",
    "haply": "haply",
}


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", "-d", choices=sorted(DEVICES), default=None)
    p.add_argument("--id", dest="master_id", default=None, help="this master's id")
    p.add_argument("--port", default=None, help="serial URL or HID path")
    p.add_argument(
        "--script", default=None, help="trajectory file (.jsonl/.csv) or a generated motion name"
    )
    p.add_argument("--rate", type=float, default=None, help="command rate (Hz, ≤ 1000)")
    p.add_argument("--scale-t", type=float, default=None)
    p.add_argument("--scale-r", type=float, default=None)
    p.add_argument("--frame", choices=["world", "tool"], default=None)
    p.add_argument(
        "--haply-url",
        default=None,
        help="haply: the Inverse Service's WebSocket (default ws://localhost:10001)",
    )


def start(ctx: ServiceContext) -> int | None:
    args = ctx.args
    overrides = {
        "device": DEVICES.get(args.device or ""),
        "master_id": args.master_id,
        "port": args.port,
        "script": args.script,
        "rate_hz": args.rate,
        "scale_t": args.scale_t,
        "scale_r": args.scale_r,
        "frame": args.frame,
        "haply_url": args.haply_url,
    }
    config = MasterConfig.from_mapping(service_table(ctx.deploy, "master", overrides))
    from services.control.master.service import MasterService

    node = ctx.open(instance=config.master_id)
    try:
        svc = MasterService(node, config)
    except DeviceNotFound as e:
        found = "\n  ".join(e.found) or "nothing"
        print(f"telerobot master: {e}\nfound:\n  {found}", file=sys.stderr)
        return CONFIG_EXIT
    ctx.closing(svc)
    ctx.log.info("master %s on %s at %.0f Hz", config.master_id, svc.device.name, config.rate_hz)
    return None


def main(argv: list[str] | None = None) -> int:
    return run_service("master", argv, start, description=__doc__, add_arguments=arguments)


if __name__ == "__main__":
    sys.exit(main())
