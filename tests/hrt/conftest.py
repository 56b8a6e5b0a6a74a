"""Fixtures of the tests of hosting an HRT loop: for the coupling patterns one live server per
module and two bridges.

Helpers that tests import live in ``pattern_support.py``, never here (tests never import
``conftest``: tests/architecture/test_test_imports.py).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator

import pytest

from rlbridge.client.bridge import Bridge
from rlbridge.server import ServerConfig, ServerThread

_topics = itertools.count()


@pytest.fixture(scope="module")
def port() -> Iterator[int]:
    with ServerThread(ServerConfig(port=0)) as srv:
        yield srv.port


@pytest.fixture
def topic() -> str:
    return f"/test/patterns/t{next(_topics)}"


@pytest.fixture
def ctl(port: int) -> Iterator[Bridge]:
    """The controller's bridge (the side that runs the HRT loop)."""
    with Bridge.connect("127.0.0.1", port, nodelay=True, name="test-ctl") as bridge:
        yield bridge


@pytest.fixture
def peer(port: int) -> Iterator[Bridge]:
    """The middleware side: publishes set-points, subscribes to outputs."""
    with Bridge.connect("127.0.0.1", port, nodelay=True, name="test-peer") as bridge:
        yield bridge
