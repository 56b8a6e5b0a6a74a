"""``python -m rlbridge.cli``, as ``python -m rlbridge``."""

from rlbridge.cli.commands import main

if __name__ == "__main__":
    main()
