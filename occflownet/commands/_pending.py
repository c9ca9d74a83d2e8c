"""Shared behaviour of verbs whose implementation has not landed yet: say so and fail, never pretend."""
import sys


def not_yet(verb: str, issue: int) -> int:
    print(f"occflownet {verb}: not implemented yet (tracked in issue {issue}).", file=sys.stderr)
    return 2
