"""``rlbridge --version``'s ``to compile:`` line names exactly the build packages missing.

setup.py builds two parts each on its own (the mypyc value path: a C compiler and Python's
headers; libsodium's cipher: the same and libsodium's headers), so an install can lack either.
The hint named ``gcc python3-dev libsodium-dev`` whatever was missing: a machine that compiled
the value path and lacked only libsodium's headers was told to install a compiler it has.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable

import pytest

from rlbridge._compiled import NOT_BUILT, PURE_ENV, STATE
from rlbridge._version import NEEDS, InstallSource, compile_hint, missing_packages, present
from rlbridge.wire.aead import NOT_BUILT as NO_LIBSODIUM
from rlbridge.wire.aead import STATE as AEAD

CHECKOUT = InstallSource("/src/rlbridge", editable=True)
PURE_WHEEL = InstallSource("/tmp/dist/rlbridge_sdk-0.1.0-py3-none-any.whl")


def _lacking(*packages: str) -> Callable[[str], bool]:
    """A machine that lacks ``packages`` and has every other."""
    return lambda package: package not in packages


def test_only_the_cipher_missing_names_libsodium_alone() -> None:
    hint = compile_hint(["cipher"], CHECKOUT, _lacking("libsodium-dev"))
    assert hint == ("apt install libsodium-dev, then pip install -e /src/rlbridge again "
                    "(without RLBRIDGE_PURE_PYTHON)")


def test_only_the_value_path_missing_never_names_libsodium() -> None:
    hint = compile_hint(["value path"], CHECKOUT,
                        _lacking("gcc", "python3-dev", "libsodium-dev"))
    assert hint.startswith("apt install gcc python3-dev, then ")
    assert "libsodium" not in hint


def test_a_package_the_machine_has_is_not_named() -> None:
    hint = compile_hint(["value path", "cipher"], PURE_WHEEL,
                        _lacking("python3-dev"))
    assert "apt install python3-dev, then pip install . from an rlbridge checkout" in hint
    assert "gcc" not in hint
    assert "libsodium" not in hint
    nothing = compile_hint(["value path", "cipher"], CHECKOUT, _lacking())
    assert nothing == "pip install -e /src/rlbridge again (without RLBRIDGE_PURE_PYTHON)"


def test_each_package_is_named_once_in_the_order_of_the_build() -> None:
    assert missing_packages(list(NEEDS), lambda _: False) == ["gcc", "python3-dev",
                                                              "libsodium-dev"]
    assert missing_packages([], lambda _: False) == []


def test_a_compiler_off_the_path_is_named_and_nothing_else() -> None:
    """The probe for real: this interpreter with a PATH that holds no compiler."""
    if not (present("python3-dev") and present("libsodium-dev")):
        pytest.skip("this machine lacks Python's or libsodium's headers")
    probe = ("from rlbridge._version import InstallSource, compile_hint\n"
             "print(compile_hint(['value path', 'cipher'], InstallSource('/c', True)))")
    proc = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                          timeout=60, check=False, env=os.environ | {"PATH": "/nonexistent"})
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == ("apt install gcc, then pip install -e /c again "
                                   "(without RLBRIDGE_PURE_PYTHON)")


def test_version_names_the_compiler_it_cannot_find_and_not_the_headers_it_has() -> None:
    """The command as a user runs it (no RLBRIDGE_PURE_PYTHON), on a PATH without gcc."""
    if STATE != NOT_BUILT and AEAD != NO_LIBSODIUM:
        pytest.skip("this install compiled both parts: --version gives no hint")
    if not (present("python3-dev") and present("libsodium-dev")):
        pytest.skip("this machine lacks Python's or libsodium's headers")
    env = {k: v for k, v in os.environ.items() if k != PURE_ENV} | {"PATH": "/nonexistent"}
    proc = subprocess.run([sys.executable, "-m", "rlbridge", "--version"], capture_output=True,
                          text=True, timeout=60, check=False, env=env)
    assert proc.returncode == 0, proc.stderr
    hint = proc.stdout.splitlines()[3]
    assert hint.startswith("to compile: apt install gcc, then "), hint
    assert "python3-dev" not in hint
    assert "libsodium" not in hint
