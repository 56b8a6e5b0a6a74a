"""Fixtures for the adapter tests: ROS 2 discovery kept on this machine, ROS peer processes.

Every ROS 2 test depends on :func:`ros_env`, which (for the whole session) sets

* ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``: DDS discovery and data stay on the loopback
  interface and shared memory; nothing is sent to other hosts or multicast on the LAN;
* ``ROS_DOMAIN_ID`` derived from the pid (1..100): two test runs on one machine (two developers,
  or CI next to a developer) do not see each other's topics; ``RLBRIDGE_TEST_ROS_DOMAIN_ID``
  picks it instead (scripts/test.sh gives each of its ROS runs its own);

and clears ``ROS_STATIC_PEERS`` so no configured peer is contacted. With
``RLBRIDGE_TEST_REQUIRE_ROS2=1`` (scripts/test.sh) a missing rclpy stops the run instead of
skipping the ROS 2 tests. ``ROS_LOG_DIR`` points into
pytest's temporary directory: rcl opens a log file per context start, which would otherwise pile
up in ``~/.ros/log``. rclpy reads these when a
context is initialised, so they must be set before any adapter or peer process starts; peer
processes inherit them. Topic names are unique per test as well, so even a domain id collision
between two runs cannot mix their results.

The helpers tests import (:class:`PeerProcess`, :func:`env_for`) live in ``ros_peers.py``:
tests never import ``conftest`` (another directory's conftest may be the one of that name).
"""

from __future__ import annotations

import importlib.util
import os
import uuid
from collections.abc import Callable, Iterator

import pytest
from ros_peers import PeerProcess

REQUIRE_ROS2 = os.environ.get("RLBRIDGE_TEST_REQUIRE_ROS2") == "1"


if REQUIRE_ROS2 and importlib.util.find_spec("rclpy") is None:
    # scripts/test.sh installed rclpy: without it the ROS 2 tests would skip, and pass unseen.
    raise pytest.UsageError("RLBRIDGE_TEST_REQUIRE_ROS2=1 but this Python has no rclpy")


@pytest.fixture(scope="session")
def ros_env(tmp_path_factory: pytest.TempPathFactory) -> Iterator[int]:
    """Scope ROS 2 discovery to this machine and this run; yields the domain id."""
    pytest.importorskip("rclpy", reason="rclpy is not installed (pip install 'rlbridge-sdk[ros2]')")
    domain_id = int(os.environ.get("RLBRIDGE_TEST_ROS_DOMAIN_ID") or 1 + os.getpid() % 100)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("ROS_LOG_DIR", str(tmp_path_factory.mktemp("ros_log")))
        mp.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        mp.setenv("ROS_DOMAIN_ID", str(domain_id))
        mp.delenv("ROS_STATIC_PEERS", raising=False)
        yield domain_id


@pytest.fixture
def unique_topic() -> Callable[[str], str]:
    """``unique_topic("x")`` -> ``/rlb_<random>_x``, the same name for the same suffix."""
    run = uuid.uuid4().hex[:8]
    return lambda suffix: f"/rlb_{run}_{suffix}"


@pytest.fixture(scope="module")
def peer(ros_env: int) -> Iterator[PeerProcess]:
    """One plain rclpy node in another process, shared by a test module."""
    process = PeerProcess()
    try:
        yield process
    finally:
        process.close()
