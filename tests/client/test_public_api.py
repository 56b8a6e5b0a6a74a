"""One import: ``rlbridge.__all__`` is the public API, loaded lazily, errors in one hierarchy."""

from __future__ import annotations

import inspect
import json
import subprocess
import sys
import types

import rlbridge
from rlbridge import errors

HEAVY = ("asyncio", "rclpy", "rlbridge.server", "rlbridge.adapters.ros2")


def _loaded_after(code: str) -> list[str]:
    """The heavy modules a fresh interpreter has loaded after running ``code``."""
    probe = (f"import sys\n{code}\n"
             f"import json; print(json.dumps(sorted(m for m in sys.modules "
             f"if m.startswith({HEAVY!r}))))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         check=True, timeout=60)
    loaded: list[str] = json.loads(out.stdout)
    return loaded


def test_the_issues_import_works() -> None:
    from rlbridge import Backoff, Bridge, LinkState, Policy, Psk, QoS, RlbridgeError, Tls

    assert all(inspect.isclass(c) for c in (Backoff, Bridge, LinkState, Policy, Psk, QoS,
                                            RlbridgeError, Tls))


def test_every_public_name_resolves_and_none_is_a_module() -> None:
    assert rlbridge.__all__ == [*sorted(rlbridge.__all__[:-1]), "__version__"]
    for name in rlbridge.__all__:
        value = getattr(rlbridge, name)
        assert not isinstance(value, types.ModuleType), f"{name} is a module, not an API"
    assert set(rlbridge.__all__) <= set(dir(rlbridge))


def test_importing_rlbridge_stays_cheap_even_after_every_name_is_used() -> None:
    """Neither asyncio (the server side) nor rclpy: a control process pays for neither."""
    assert _loaded_after("import rlbridge") == []
    assert _loaded_after("import rlbridge\nfor n in rlbridge.__all__: getattr(rlbridge, n)") == []


def test_every_exception_is_exported_and_rooted_in_rlbridge_error() -> None:
    defined = {name: value for name, value in vars(errors).items()
               if inspect.isclass(value) and issubclass(value, Exception)
               and value.__module__ == errors.__name__}
    assert len(defined) > 30
    for name, cls in defined.items():
        if issubclass(cls, Warning):
            assert name == "RealTimeWarning"
            continue
        assert issubclass(cls, errors.RlbridgeError), name
        assert name in rlbridge.__all__ or name == "AuthRefused", name
    # The branches a program catches by kind.
    assert issubclass(errors.TlsFailed, errors.ConnectionFailed)
    assert issubclass(errors.AuthenticationFailed, errors.SessionError)
    assert issubclass(errors.LinkLost, errors.ChannelError)
    assert issubclass(errors.TypeClashError, errors.BindingRefused)
    assert issubclass(errors.WrongValueType, errors.ValueRejected)
    assert issubclass(errors.WrongValueType, TypeError)
    assert issubclass(errors.ServiceTimeout, errors.ServiceError)
    assert issubclass(errors.ParameterError, errors.ServiceError)
    assert isinstance(errors.error_from_code(errors.ErrorCode.NO_SERVICE, "none"),
                      errors.NoServiceError)
