"""The package version and the distribution name, each in one place, and where this copy was
installed from, so that every install hint says what applies to it.

The import package and the command are ``rlbridge``; the distribution (what ``pip install``
takes) is ``rlbridge-sdk``, because ``rlbridge`` on PyPI is an unrelated project, and
``rlbridge-sdk`` is not on PyPI either: a hint naming ``pip install 'rlbridge-sdk[ros2]'``
cannot work, and "pip install again" cannot change a pure-Python wheel (``py3-none-any``:
nothing in it compiles). pip records where it installed a distribution from (PEP 610,
``direct_url.json``): an editable checkout, a checkout directory, or a wheel file.
:func:`install_source` reads it; :func:`pip_install` and :func:`compile_hint` word their
advice for that source, and the latter names only the build packages this machine lacks.
Standard library only: setup.py and every part may import this.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from urllib.parse import unquote, urlparse

__version__ = "0.1.0"

#: The name pip knows this project by (pyproject.toml ``[project] name``).
DISTRIBUTION = "rlbridge-sdk"

#: What to build on when the source is unknown (a copy of the files, a distribution package).
_FROM_CHECKOUT = "from an rlbridge checkout"


@dataclass(frozen=True)
class InstallSource:
    """Where pip installed this copy from: ``path`` (a directory or a ``.whl``), and whether
    the install is editable (``pip install -e``: the checkout's files run in place)."""

    path: str
    editable: bool = False

    @property
    def wheel(self) -> bool:
        """Installed from a wheel file (on a board: the one the README's command builds)."""
        return self.path.endswith(".whl")

    @property
    def pure_wheel(self) -> bool:
        """A ``py3-none-any`` wheel: no compiled module in it, and installing it again adds
        none (only building a new wheel on a machine with the compilers does)."""
        return self.wheel and self.path.endswith("-none-any.whl")


def source_of(direct_url: str | None) -> InstallSource | None:
    """The source a ``direct_url.json`` text names, None for none or one not on this machine."""
    if not direct_url:
        return None
    try:
        info = json.loads(direct_url)
    except ValueError:
        return None
    url = str(info.get("url", "")) if isinstance(info, dict) else ""
    if not url.startswith("file://"):
        return None
    editable = bool((info.get("dir_info") or {}).get("editable", False))
    return InstallSource(unquote(urlparse(url).path), editable)


def install_source() -> InstallSource | None:
    """This process's ``rlbridge-sdk``: where pip installed it from, None when unknown."""
    from importlib import metadata

    try:
        text = metadata.distribution(DISTRIBUTION).read_text("direct_url.json")
    except metadata.PackageNotFoundError:
        return None
    return source_of(text)


def pip_install(extra: str, source: InstallSource | None = None) -> str:
    """The command that adds an optional extra (``plot``, ``ros2``) to this install; every
    install hint the code prints comes from here, so none can name the wrong project.

    ``source`` defaults to :func:`install_source`; the command names the checkout or wheel
    this copy came from (the distribution is not on PyPI, so its name alone installs nothing).
    """
    if source is None:
        source = install_source()
    if source is None:
        return f"pip install -e '.[{extra}]' {_FROM_CHECKOUT} (or the wheel you installed, " \
               f"with [{extra}] after its file name)"
    return f"pip install {'-e ' if source.editable else ''}'{source.path}[{extra}]'"


#: What setup.py needs to build each part, as Debian and Ubuntu name the packages: mypyc's
#: value path a C compiler and Python's headers, libsodium's cipher (a C extension) the same
#: and libsodium's headers.
NEEDS: dict[str, tuple[str, ...]] = {
    "value path": ("gcc", "python3-dev"),
    "cipher": ("gcc", "python3-dev", "libsodium-dev"),
}


def present(package: str) -> bool:
    """Whether this machine has what ``package`` (one named in :data:`NEEDS`) gives a build
    now: the C compiler Python was built with (or ``gcc``, ``cc``) on the ``PATH``, this
    interpreter's ``Python.h``, libsodium's ``sodium.h``."""
    import shutil
    import sysconfig
    from pathlib import Path

    if package == "gcc":
        configured = str(sysconfig.get_config_var("CC") or "").split()
        return any(shutil.which(cc) for cc in (*configured[:1], "gcc", "cc"))
    if package == "python3-dev":
        return Path(sysconfig.get_paths()["include"], "Python.h").is_file()
    dirs = ["/usr/include", "/usr/local/include", str(sysconfig.get_config_var("INCLUDEDIR"))]
    return any(Path(d, "sodium.h").is_file() for d in dirs)


def missing_packages(unbuilt: Sequence[str],
                     have: Callable[[str], bool] = present) -> list[str]:
    """The packages the ``unbuilt`` parts (keys of :data:`NEEDS`) need that this machine
    lacks, each once: with the value path compiled and only the cipher missing, that is
    ``libsodium-dev`` alone (the compiler and headers are evidently there)."""
    wanted = dict.fromkeys(p for part in unbuilt for p in NEEDS[part])
    return [p for p in wanted if not have(p)]


def compile_hint(unbuilt: Sequence[str] = tuple(NEEDS), source: InstallSource | None = None,
                 have: Callable[[str], bool] = present) -> str:
    """What builds the ``unbuilt`` parts (the compiled value path, libsodium's cipher) into
    this install, naming only the packages this machine lacks for them.

    An editable checkout or a checkout directory: those packages, then installing from it
    again. A pure wheel: nothing installed from it compiles, so a wheel built on a machine
    like this one (or an install from a checkout) is the way.
    """
    if source is None:
        source = install_source()
    missing = missing_packages(unbuilt, have)
    tools = f"apt install {' '.join(missing)}, then " if missing else ""
    if source is not None and not source.wheel:
        again = f"pip install {'-e ' if source.editable else ''}{source.path}"
        return f"{tools}{again} again (without RLBRIDGE_PURE_PYTHON)"
    if source is not None and source.pure_wheel:
        return (f"this is a pure-Python wheel ({source.path.rsplit('/', 1)[-1]}): installing "
                f"it again changes nothing; {tools}pip install . {_FROM_CHECKOUT} on "
                "this machine (README, Install)")
    return f"{tools}pip install . {_FROM_CHECKOUT} on this machine (README, Install)"
