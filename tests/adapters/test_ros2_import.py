"""Importing: rclpy only when the ROS 2 adapter is asked for, and a clear message without it."""

from __future__ import annotations

import subprocess
import sys

import pytest


def _run(code: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=False
    )


def test_importing_rlbridge_does_not_import_rclpy() -> None:
    result = _run(
        "import sys, rlbridge, rlbridge.adapters, rlbridge.adapters.base, "
        "rlbridge.adapters.inproc\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in "
        "('rclpy', 'rosidl_parser', 'rosidl_generator_py', 'std_msgs')))"
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"


def test_without_rclpy_the_import_error_says_what_to_install() -> None:
    # sys.modules[name] = None makes ``import name`` fail as if it were not installed.
    result = _run(
        "import sys\n"
        "sys.modules['rclpy'] = None\n"
        "try:\n"
        "    import rlbridge.adapters.ros2\n"
        "except ImportError as exc:\n"
        "    print('ImportError:', exc)\n"
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("ImportError:")
    assert "pip install -e '" in result.stdout  # this checkout: rlbridge-sdk is not on PyPI
    assert "[ros2]'" in result.stdout


def test_without_rclpy_serve_says_so_in_one_line_naming_rclpy() -> None:
    """Not nested inside itself, and not naming a module the user never heard of."""
    result = _run(
        "import sys\n"
        "sys.modules['rclpy'] = None\n"
        "sys.modules['rosidl_generator_py'] = None\n"
        "from rlbridge.adapters import AdapterUnavailable, load_adapter\n"
        "try:\n"
        "    load_adapter('ros2')\n"
        "except AdapterUnavailable as exc:\n"
        "    print(exc)\n"
    )
    assert result.returncode == 0, result.stderr
    assert len(result.stdout.splitlines()) == 1, result.stdout
    line = result.stdout.strip()
    assert line.startswith("the ros2 adapter needs rclpy, which is not installed: pip install ")
    assert line.count("rclpy") == 1
    assert "rosidl" not in line


@pytest.mark.ros2
def test_importing_the_adapter_is_warning_free(ros_env: int) -> None:
    """rosidl's lark import warns (sre_parse); the adapter silences exactly that, once."""
    result = _run(
        "import warnings\n"
        "warnings.simplefilter('error')\n"
        "from rlbridge.adapters.ros2 import Ros2Adapter\n"
        "from rlbridge.adapters.base import QoS\n"
        f"with Ros2Adapter('rlbridge_warnings', domain_id={ros_env}) as a:\n"
        "    a.create_publisher('/rlb_w', 'geometry_msgs/msg/Twist', None, QoS())\n"
        "print('ok')\n"
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "ok"
