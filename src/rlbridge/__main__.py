"""``python -m rlbridge``: the same as the ``rlbridge`` command (useful without the venv's bin/)."""

from rlbridge.cli import main

if __name__ == "__main__":
    main()
