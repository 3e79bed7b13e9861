"""The person's hands at a master station: in-process (DeviceLink) and over the bus
(BusLink, robot/master/<id>/rpc/set_hand); the knobs go through the master's methods."""

from __future__ import annotations

import numpy as np
import pytest

from services.control.master.config import MasterConfig
from services.control.master.devices.virtual import VirtualMaster
from services.control.master.service import MasterService
from services.geometry import rot_z
from services.tools.tasks.operator import BusLink, DeviceLink, MasterLink
from tests.conftest import Net


@pytest.mark.parametrize("kind", ["device", "bus"])
def test_a_link_moves_the_hand_and_turns_the_knobs(net: Net, kind: str) -> None:
    device = VirtualMaster()
    cfg = MasterConfig(master_id="op", device="virtual", engage_on_start=False)
    master = MasterService(net.node("master", "op"), cfg, device)
    try:
        node = net.node("tasks")
        link: MasterLink = (
            DeviceLink(device, node, "op") if kind == "device" else BusLink(node, "op")
        )
        R = rot_z(0.3)
        link.set_hand(np.array([0.01, 0.02, 0.03]), R, True, 1.0)
        reading = device.read(0.01)
        np.testing.assert_allclose(reading.hand_p, [0.01, 0.02, 0.03])
        np.testing.assert_allclose(reading.hand_R, R, atol=1e-12)
        assert reading.clutch is True and reading.grip == 1.0
        status = link.set_scale(0.25, 0.5)
        assert (status["scale_t"], status["scale_r"]) == (0.25, 0.5)
        assert link.set_frame("tool")["frame"] == "tool"
    finally:
        master.close()
