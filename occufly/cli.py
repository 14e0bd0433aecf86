"""The ``occufly`` command line."""
import sys


def main(argv: list[str] | None = None) -> int:
    print("occufly: under construction", file=sys.stderr)
    return 0
