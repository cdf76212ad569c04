"""`MrrigError`: the base of every ordinary error of mrrig (bad input, a rig that cannot go on).

The contract: the message is one line naming what was wrong (the file and field, the request,
the frame), so that the command line prints it as `error: ...` and a log keeps it on one line.
A message given with line breaks is joined into one line. Each error also derives from the
builtin it refines (ValueError, RuntimeError, ConnectionError, ...), so callers that catch
those keep working.
"""

from __future__ import annotations


class MrrigError(Exception):
    """An ordinary error: printed by the command line as one `error: ...` line."""

    def __str__(self) -> str:
        return " ".join(line.strip() for line in super().__str__().splitlines() if line.strip())
