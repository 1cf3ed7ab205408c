"""Small option parsers shared by the verb modules (standard library only)."""

from __future__ import annotations

from tergodic_cli.errors import TergodicError


def parse_floats(text: str, n: int | None, option: str, example: str) -> tuple[float, ...]:
    """Parse ``"a,b,c"`` into ``n`` floats (any count when ``n`` is None) or raise a one-line error naming ``option``."""
    try:
        values = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise TergodicError(f"{option} '{text}' is not {n} comma-separated numbers", f"e.g. {option} {example}") from None
    if n is not None and len(values) != n:
        raise TergodicError(f"{option} needs {n} numbers, got {len(values)}", f"e.g. {option} {example}")
    return values
