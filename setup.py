"""Build: the pure-Python package, plus its value path compiled by mypyc when that works.

Everything else is in pyproject.toml. ``pip install .`` and ``pip install -e .`` compile the
modules listed in ``src/rlbridge/_compiled.py`` (about a minute of CPU) and record each
source's SHA-256 beside them; the package then runs them compiled (``rlbridge --version`` says
so). Compiling never fails the install: without a C compiler or Python headers, or if mypyc
refuses the code, the build says why and installs the plain package, which works the same,
slower (docs/benchmarks.md, "Compiled value path"). ``RLBRIDGE_PURE_PYTHON=1`` skips
compiling (a portable ``py3-none-any`` wheel for another machine, or a faster install).
"""

from __future__ import annotations

import json
import os
import runpy
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any

from setuptools import setup
from setuptools.command.build_ext import build_ext

ROOT = Path(__file__).resolve().parent
COMPILED = runpy.run_path(str(ROOT / "src" / "rlbridge" / "_compiled.py"))
MODULES: tuple[str, ...] = COMPILED["MODULES"]


#: Where mypyc writes the C code of this build (removed after it).
C_DIR = os.path.join("build", f"mypyc-{os.getpid()}")


def _say(message: str) -> None:
    """pip shows a build's output with ``-v`` (and on failure)."""
    print(f"rlbridge build: {message}", file=sys.stderr, flush=True)


def _sources() -> list[str]:
    return [str(Path("src", *m.split(".")).with_suffix(".py")) for m in MODULES]


#: The commands that build extensions; pip runs setup.py for metadata too (egg_info), where
#: mypyc's type check (most of its time) would be wasted.
BUILDS = {"build", "build_ext", "bdist_wheel", "editable_wheel", "install", "develop"}


def _extensions() -> list[Any]:
    """mypyc's extensions for :data:`MODULES`, or none (the pure package) if it cannot."""
    if not BUILDS.intersection(sys.argv[1:]):
        return []
    if COMPILED["pure_requested"](os.environ):
        _say(f"{COMPILED['PURE_ENV']} is set: not compiling, the package is pure Python")
        return []
    try:
        from mypyc.build import mypycify
    except ImportError as exc:
        _say(f"mypyc is not available ({exc}): the package is pure Python")
        return []
    # Type-checked without the dependencies (the isolated build environment has none; their
    # types are Any here, which changes nothing mypyc makes of rlbridge's own code) and without
    # pyproject's pydantic plugin; `mypy --strict src` is what checks the types.
    config = Path(tempfile.mkdtemp(prefix="rlbridge-mypy-")) / "mypy.ini"
    config.write_text("[mypy]\nignore_missing_imports = True\nfollow_imports = silent\n")
    try:
        # C files of a build of their own (CI builds for several Pythons at once in one
        # checkout); relative, as setuptools wants every source path.
        return list(mypycify(["--config-file", str(config), *_sources()], opt_level="3",
                             group_name="rlbridge", target_dir=C_DIR))
    except (Exception, SystemExit) as exc:  # mypy exits on a type error
        _say(f"mypyc refused the code ({exc!r}): the package is pure Python")
        return []


class OptionalBuildExt(build_ext):
    """Builds the compiled modules, or none of them: a failure leaves the pure package."""

    def finalize_options(self) -> None:
        super().finalize_options()
        self.build_temp = tempfile.mkdtemp(prefix="rlbridge-build-")  # see _extensions

    def run(self) -> None:
        if not self.extensions:  # not compiling (see _extensions): nothing to record
            return
        try:
            super().run()
        except Exception as exc:  # no compiler, no Python.h, a compile or link error
            self._discard()
            _say(f"compiling failed ({exc}): the package is pure Python")
            return
        finally:
            shutil.rmtree(C_DIR, ignore_errors=True)
        self._record()
        _say(f"compiled {len(MODULES)} modules with mypyc")

    def _package_dirs(self) -> list[Path]:
        """Where the package is built (the wheel's tree) and, editable, the source tree."""
        dirs = [Path(self.build_lib, "rlbridge")]
        if self.inplace or getattr(self, "editable_mode", False):
            dirs.append(Path(self.get_finalized_command("build_py").get_package_dir("rlbridge")))
        return dirs

    def _discard(self) -> None:
        """No half build: the compiled modules import each other's code from one library."""
        for output in self.get_outputs():
            Path(output).unlink(missing_ok=True)

    def _record(self) -> None:
        """Each compiled source's SHA-256, so a later edit runs as Python (_compiled.py)."""
        digest = COMPILED["digest"]
        digests = {m: digest(ROOT / p) for m, p in zip(MODULES, _sources(), strict=True)}
        for package_dir in self._package_dirs():
            if package_dir.is_dir():
                (package_dir / COMPILED["SOURCES_FILE"]).write_text(
                    json.dumps(digests, indent=1, sort_keys=True) + "\n")


setup(ext_modules=_extensions(), cmdclass={"build_ext": OptionalBuildExt})
