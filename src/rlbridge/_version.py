"""The package version and the distribution name, each in one place.

The import package and the command are ``rlbridge``; the distribution (what ``pip install``
takes) is ``rlbridge-sdk``, because ``rlbridge`` on PyPI is an unrelated project. Every
install hint the code prints comes from :func:`pip_install` so none can name the wrong one.
"""

__version__ = "0.1.0"

#: The name pip knows this project by (pyproject.toml ``[project] name``).
DISTRIBUTION = "rlbridge-sdk"


def pip_install(extra: str) -> str:
    """The command that adds an optional extra (``plot``, ``ros2``) to this install: from the
    checkout or wheel it came from, since the distribution is not on PyPI (rlbridge._install)."""
    from rlbridge._install import pip_install as for_this_install

    return for_this_install(extra)
