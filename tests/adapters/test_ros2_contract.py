"""The adapter contract, run on the ROS 2 adapter (one fresh rclpy context per test)."""

from __future__ import annotations

import pytest
from contract import AdapterContract
from contract_services import ServiceContract

from rlbridge.adapters.base import MiddlewareAdapter

ros2 = pytest.importorskip(
    "rlbridge.adapters.ros2",
    reason="rclpy is not installed (pip install 'rlbridge-sdk[ros2]')",
    exc_type=ImportError,
)

pytestmark = pytest.mark.ros2


class TestRos2Contract(AdapterContract, ServiceContract):
    #: ROS 2 services have no error reply: a failing provider leaves the caller to time out.
    provider_failure = "TIMEOUT"

    @pytest.fixture(autouse=True)
    def _scoped_discovery(self, ros_env: int) -> None:
        self.domain_id = ros_env

    def make_adapter(self) -> MiddlewareAdapter:
        adapter: MiddlewareAdapter = ros2.Ros2Adapter("rlbridge_contract", domain_id=self.domain_id)
        return adapter
