"""Build: the pure-Python package, plus its value path compiled by mypyc and libsodium's cipher
when that works.

Everything else is in pyproject.toml. ``pip install .`` and ``pip install -e .`` compile the
modules listed in ``src/rlbridge/_compiled.py`` (about a minute of CPU) and record each
source's SHA-256 beside them; the package then runs them compiled (``rlbridge --version`` says
so). They also build ``rlbridge.wire._chacha``, ChaCha20-Poly1305 from libsodium for sealed
sessions (``src/rlbridge/wire/aead.py`` says why), when libsodium's headers are installed
(Debian: ``apt install libsodium-dev``). Each of the two is optional, on its own: compiling
never fails the install. Without a C compiler or Python headers, if mypyc refuses the code or
libsodium is missing, the build says why and installs without it; the package works the same,
slower (docs/benchmarks.md, "Compiled value path" and "Cost of encryption").
``RLBRIDGE_PURE_PYTHON=1`` compiles nothing (a portable ``py3-none-any`` wheel for another
machine, or a faster install).
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

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

ROOT = Path(__file__).resolve().parent
COMPILED = runpy.run_path(str(ROOT / "src" / "rlbridge" / "_compiled.py"))
MODULES: tuple[str, ...] = COMPILED["MODULES"]


#: libsodium's ChaCha20-Poly1305 for sealed sessions (built apart from the mypyc modules).
CIPHER = Extension("rlbridge.wire._chacha", sources=["src/rlbridge/wire/_chacha.c"],
                   libraries=["sodium"])

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
    """The cipher and mypyc's extensions for :data:`MODULES`, or none (the pure package)."""
    if not BUILDS.intersection(sys.argv[1:]):
        return []
    if COMPILED["pure_requested"](os.environ):
        _say(f"{COMPILED['PURE_ENV']} is set: not compiling, the package is pure Python")
        return []
    return [CIPHER, *_mypyc_extensions()]


def _mypyc_extensions() -> list[Any]:
    """mypyc's extensions for :data:`MODULES`, or none if it cannot."""
    try:
        from mypyc.build import mypycify
    except ImportError as exc:
        _say(f"mypyc is not available ({exc}): the value path is pure Python")
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
        _say(f"mypyc refused the code ({exc!r}): the value path is pure Python")
        return []


class OptionalBuildExt(build_ext):
    """Builds the cipher, and the compiled modules or none of them, each part on its own: a
    part that fails is discarded and dropped from the build's list, so setuptools neither
    copies it (an editable install copies every listed extension into the source tree, and a
    missing one would fail the whole build) nor records it; the Python it falls back to is
    always installed."""

    def finalize_options(self) -> None:
        super().finalize_options()
        self.build_temp = tempfile.mkdtemp(prefix="rlbridge-build-")  # see _extensions

    def run(self) -> None:
        if not self.extensions:  # not compiling (see _extensions): nothing to record
            self._remove_stale([])
            return
        try:
            super().run()  # set-up, build_extensions below, then (editable) the copies
        except Exception as exc:  # no compiler or no Python.h: nothing could be built
            self._give_up(self.extensions, f"compiling failed ({exc}): the package is pure "
                          "Python and seals with cryptography's ChaCha20-Poly1305")
        finally:
            shutil.rmtree(C_DIR, ignore_errors=True)

    def build_extensions(self) -> None:
        self.check_extensions_list(self.extensions)
        cipher = [e for e in self.extensions if e is CIPHER]
        mypyc = [e for e in self.extensions if e is not CIPHER]
        if self._build_part(cipher, "not building rlbridge.wire._chacha ({}; Debian: apt "
                            "install libsodium-dev): sealed sessions use cryptography's "
                            "ChaCha20-Poly1305"):
            _say("built rlbridge.wire._chacha (libsodium's ChaCha20-Poly1305)")
        if self._build_part(mypyc, "compiling failed ({}): the value path is pure Python"):
            self._record()
            _say(f"compiled {len(MODULES)} modules with mypyc")
        self._remove_stale(self.extensions)

    def _build_part(self, part: list[Any], failed: str) -> bool:
        """Build one part whole (True), or leave no trace of it in the build (False)."""
        if not part:
            return False
        try:
            for ext in part:
                self.build_extension(ext)
        except Exception as exc:  # a compile or link error (the cipher's: most often no sodium.h)
            self._give_up(part, failed.format(exc))
            return False
        return True

    def _give_up(self, part: list[Any], why: str) -> None:
        """No half build: the compiled modules import each other's code from one library."""
        for ext in part:
            Path(self.get_ext_fullpath(ext.name)).unlink(missing_ok=True)
        self.extensions = [e for e in self.extensions if e not in part]
        _say(why)

    def _package_dirs(self) -> list[Path]:
        """Where the package is built (the wheel's tree) and, editable, the source tree."""
        dirs = [Path(self.build_lib, "rlbridge")]
        if self.inplace or getattr(self, "editable_mode", False):
            dirs.append(Path(self.get_finalized_command("build_py").get_package_dir("rlbridge")))
        return dirs

    def _remove_stale(self, built: list[Any]) -> None:
        """Remove this interpreter's extensions in the package that this build did not make:
        in an editable checkout, one left from an earlier build (a module no longer compiled)
        would shadow its ``.py``. Other Pythons' builds (other suffixes) are theirs."""
        suffix = str(self.get_ext_filename("x"))[1:]  # e.g. .cpython-311-x86_64-linux-gnu.so
        keep = {ext.name for ext in built}
        for package_dir in self._package_dirs():
            for path in package_dir.rglob(f"*{suffix}"):
                module = ".".join(("rlbridge", *path.relative_to(package_dir).parts))
                if module[: -len(suffix)] not in keep:
                    _say(f"removing {path} (not built this time)")
                    path.unlink()

    def _record(self) -> None:
        """Each compiled source's SHA-256, so a later edit runs as Python (_compiled.py)."""
        digest = COMPILED["digest"]
        digests = {m: digest(ROOT / p) for m, p in zip(MODULES, _sources(), strict=True)}
        for package_dir in self._package_dirs():
            if package_dir.is_dir():
                (package_dir / COMPILED["SOURCES_FILE"]).write_text(
                    json.dumps(digests, indent=1, sort_keys=True) + "\n")


setup(ext_modules=_extensions(), cmdclass={"build_ext": OptionalBuildExt})
