"""Text that others gave (a client's claimed user and host, a plan's step names, a fault's
reason, a file name) on its way to a log line, a terminal, an XML report, a figure or the
catalog: one line, bounded, printable, and literal.

`one_line` escapes what could forge a second log line or drive a terminal (control characters,
line and paragraph separators, bidirectional overrides, lone surrogates, non-characters) as
visible `\\xNN` / `\\uNNNN` text, and cuts a long text with a mark that says how much was left
out: what is kept is still there to read, and nothing acts. `plot_literal` makes matplotlib
draw a text as it is (a `$` is not the start of mathtext).
"""

from __future__ import annotations

import unicodedata
from typing import Any

MAX_CHARS = 256  # a name, a user, a host: more than any real one

# bidirectional embeddings, overrides and isolates: they reorder what a terminal shows
_BIDI = frozenset("\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069\u200e\u200f")


def _acts(c: str) -> bool:
    cat = unicodedata.category(c)
    if cat in ("Cc", "Cs", "Zl", "Zp") or c in _BIDI:
        return True
    return cat == "Cn" and (ord(c) & 0xFFFE) == 0xFFFE  # U+FFFE, U+FFFF, ...: not XML


def _escape(c: str) -> str:
    code = ord(c)
    return f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}"


def one_line(value: Any, max_chars: int = MAX_CHARS) -> str:
    """`value` as one printable line of at most about `max_chars` characters: characters that
    act (control, line breaks, bidi, surrogates) escaped as visible text, and a longer text cut
    with a mark naming how many characters were left out."""
    text = value if isinstance(value, str) else str(value)
    out: list[str] = []  # one piece per character kept
    size = 0
    for c in text[:max_chars]:
        piece = _escape(c) if _acts(c) else c
        if size + len(piece) > max_chars:
            break
        out.append(piece)
        size += len(piece)
    left = len(text) - len(out)
    return "".join(out) + (f"...[{left} more characters]" if left else "")


def plot_literal(text: Any) -> str:
    """`text` (one line, bounded) as matplotlib draws it literally: `$` escaped, so that a
    step called `$x^$` is neither typeset as math nor an error of the mathtext parser."""
    return one_line(text, 4 * MAX_CHARS).replace("$", r"\$")
