"""The adapter contract, run on the in-process bus (the reference implementation)."""

from __future__ import annotations

from contract import AdapterContract
from contract_services import ServiceContract

from rlbridge.adapters.base import MiddlewareAdapter
from rlbridge.adapters.inproc import InProcessBus


class TestInProcessContract(AdapterContract, ServiceContract):
    timeout = 2.0

    def make_adapter(self) -> MiddlewareAdapter:
        return InProcessBus()
