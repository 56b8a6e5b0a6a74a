"""Module size is a prompt for judgement, not a rule: one idea per module is the rule.

A line cap cut single ideas in two (a class and its mixin, a Protocol mirroring a class) to
fit, which is worse than a long module that holds one idea. So nothing here fails on length;
the check prints the modules over :data:`NOTE_AT` lines (``pytest -s`` shows it), so a reviewer
asks of each whether it holds a second idea (docs/design.md, "The map") and splits it where
the ideas part, if they do.
"""

from __future__ import annotations

from import_graph import PACKAGE, SUITES, modules

#: Lines above which a module is named in the note.
NOTE_AT = 600


def sizes() -> dict[str, int]:
    """``module -> lines`` of every module of the package and of the suites."""
    found = {**modules(PACKAGE), **modules(SUITES)}
    return {name: len(path.read_text().splitlines()) for name, path in sorted(found.items())}


def test_long_modules_are_named_for_review() -> None:
    counted = sizes()
    # The count covers both trees (a note over nothing would say nothing).
    assert counted["rlbridge.csp.ring"] > 0
    assert any(m.startswith("benchmarks.") for m in counted)
    long = {name: n for name, n in counted.items() if n > NOTE_AT}
    if long:
        print(f"\nmodules over {NOTE_AT} lines (does each hold one idea?): "
              + ", ".join(f"{name} ({n})" for name, n in long.items()))
