""".dockerignore keeps the build context small without starving the Dockerfile's COPY lines.

No Docker engine runs here, so the patterns are applied the way Docker documents them
(https://docs.docker.com/build/concepts/context/#dockerignore-files): paths relative to the
context root, ``*`` within one path segment, ``**`` across any number of them, a pattern that
matches a directory excludes everything under it, ``!`` re-includes, and the last matching
line wins.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path
from typing import Any

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]


def _regex(pattern: str) -> re.Pattern[str]:
    out = ""
    i = 0
    while i < len(pattern):
        if pattern.startswith("**/", i):
            out += "(?:.*/)?"
            i += 3
        elif pattern.startswith("**", i):
            out += ".*"
            i += 2
        elif pattern[i] == "*":
            out += "[^/]*"
            i += 1
        elif pattern[i] == "?":
            out += "[^/]"
            i += 1
        elif pattern[i] == "[":
            end = pattern.index("]", i)
            out += pattern[i:end + 1]
            i = end + 1
        else:
            out += re.escape(pattern[i])
            i += 1
    return re.compile(out)


def parse_dockerignore(text: str) -> list[tuple[bool, re.Pattern[str]]]:
    """``(negated, regex)`` per pattern line, in file order."""
    rules = []
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        negated = line.startswith("!")
        line = line.removeprefix("!").strip().strip("/")
        rules.append((negated, _regex(line)))
    return rules


def excluded(path: str, rules: list[tuple[bool, re.Pattern[str]]]) -> bool:
    """Whether ``path`` (relative, ``/``-separated) stays out of the build context."""
    parts = path.split("/")
    prefixes = ["/".join(parts[:n]) for n in range(1, len(parts) + 1)]
    result = False
    for negated, rx in rules:
        if any(rx.fullmatch(p) for p in prefixes):
            result = not negated
    return result


@pytest.fixture(scope="module")
def rules() -> list[tuple[bool, re.Pattern[str]]]:
    return parse_dockerignore((REPO / ".dockerignore").read_text(encoding="utf-8"))


def _contexts() -> set[Path]:
    compose: dict[str, Any] = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    contexts = set()
    for service in compose["services"].values():
        build = service.get("build")
        if build is None:
            continue
        ctx = build if isinstance(build, str) else build.get("context", ".")
        contexts.add((REPO / ctx).resolve())
    return contexts


def _copy_sources() -> list[str]:
    lines = [line for line in (REPO / "Dockerfile").read_text().splitlines()
             if not line.lstrip().startswith("#")]
    sources = []
    for line in "\n".join(lines).replace("\\\n", " ").splitlines():
        words = shlex.split(line)
        if not words or words[0].upper() not in ("COPY", "ADD"):
            continue
        args = [w for w in words[1:] if not w.startswith("--")]
        if any(w.startswith("--from") for w in words[1:]):
            continue  # from another stage, not from the context
        sources += args[:-1]
    return sources


def test_the_compose_file_builds_from_the_repository_root() -> None:
    assert _contexts() == {REPO.resolve()}, "update this test if the build context moves"


def test_parser_follows_docker_semantics() -> None:
    rules = parse_dockerignore("# c\n/out/\n**/*.pyc\ndocs\n!docs/keep.md\nsrc/*/tmp\n")
    assert excluded("out/x/y.png", rules)
    assert excluded("a/b/c.pyc", rules)
    assert excluded("c.pyc", rules)
    assert excluded("docs/a.md", rules)
    assert not excluded("docs/keep.md", rules)
    assert excluded("src/pkg/tmp/f", rules)
    assert not excluded("src/tmp", rules)
    assert not excluded("outside.txt", rules)
    assert not excluded("output/x", rules)


def test_context_includes_what_the_dockerfile_copies(
        rules: list[tuple[bool, re.Pattern[str]]]) -> None:
    sources = _copy_sources()
    assert {"pyproject.toml", "src"} <= set(sources)
    for source in sources:
        assert (REPO / source).exists(), f"Dockerfile copies {source}, which does not exist"
        assert not excluded(source, rules), f".dockerignore excludes {source}, which is COPYed"
    for path in sorted((REPO / "src").rglob("*")):
        if path.is_file() and "__pycache__" not in path.parts and path.suffix != ".pyc" \
                and not any(p.endswith(".egg-info") for p in path.parts):
            rel = path.relative_to(REPO).as_posix()
            assert not excluded(rel, rules), f".dockerignore drops {rel} from the image"


def test_context_leaves_out_the_heavy_and_the_local(
        rules: list[tuple[bool, re.Pattern[str]]]) -> None:
    for path in (".venv/bin/python", ".git/HEAD", "out/pan_tilt.png", "pan_tilt.png",
                 "src/rlbridge/__pycache__/cli.cpython-311.pyc", ".mypy_cache/x",
                 ".pytest_cache/v", "docs/figures/jitter.png", "src/rlbridge.egg-info/PKG-INFO"):
        assert excluded(path, rules), f"{path} would be sent to the Docker daemon"
