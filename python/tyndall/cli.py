"""The ``tyndall`` command: runs the Rust command line (same code as the cargo binary)."""

from __future__ import annotations

import sys

from ._native import cli_main


def main() -> None:
    """Entry point of the ``tyndall`` console script."""
    sys.exit(cli_main(["tyndall", *sys.argv[1:]]))


if __name__ == "__main__":
    main()
