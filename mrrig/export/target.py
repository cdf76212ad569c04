"""Where an export may be written (`mrrig export --out`): never over a file that is there
unless asked (`force`), never through a symbolic link, and never over a run catalog (SQLite,
its WAL) or a recording (.rrd), asked or not: those hold runs that are not anywhere else.

The file is written under a temporary name in its folder (created new: O_EXCL, so never
through a link) and put in place by one rename, which replaces a name and follows nothing;
without `force` it is put in place by a hard link, which fails where the name has been taken
meanwhile. A reader never sees half an export, and a failed one leaves nothing behind.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

from mrrig.errors import MrrigError

# what a file starts with where it holds runs: an SQLite database, its WAL, a Rerun recording
_PRECIOUS = (
    (b"SQLite format 3\x00", "a database (a run catalog?)"),
    (b"\x37\x7f\x06\x82", "an SQLite write-ahead log (a run catalog's)"),
    (b"\x37\x7f\x06\x83", "an SQLite write-ahead log (a run catalog's)"),
    (b"RRF2", "a Rerun recording"),
)


class OutputError(MrrigError, OSError):
    """An output file that must not be written (there already, a link, a catalog, ...)."""


def check_target(out: Path, force: bool, protected: tuple[Path, ...] = ()) -> None:
    """Refuse `out` (OutputError, one line) where it is a symbolic link, a catalog or a
    recording (by its first bytes, or one of `protected`), or there already without `force`."""
    if out.is_symlink():
        raise OutputError(
            f"{out} is a symbolic link (to {os.readlink(out)}): an export never writes through"
            " one; give the file's own path"
        )
    real = out.resolve()
    for path in protected:
        if path.resolve() == real:
            raise OutputError(f"{out} is {path}, which holds runs: give another --out")
    if not out.exists():
        return
    if not out.is_file():
        raise OutputError(f"{out} is there and is not a file")
    head = _head(out)
    for magic, what in _PRECIOUS:
        if head.startswith(magic):
            raise OutputError(f"{out} is {what}: an export never writes over one, --force or not")
    if not force:
        raise OutputError(f"{out} is there already: --force to replace it")


def write_new(out: Path, force: bool, write: Callable[[Path], None]) -> Path:
    """`write(tmp)` a temporary file beside `out`, then put it at `out` (replacing a file
    only with `force`); `check_target` first. Returns `out`."""
    check_target(out, force)
    fd, name = tempfile.mkstemp(prefix=f".{out.name}.", suffix=out.suffix, dir=out.parent)
    tmp = Path(name)
    try:
        os.close(fd)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # as a plain open() would have made it
        write(tmp)
        check_target(out, force)  # again: the name may have changed while it was written
        if force:
            os.replace(tmp, out)
        else:
            try:
                os.link(tmp, out)
            except FileExistsError:
                raise OutputError(f"{out} is there already: --force to replace it") from None
            except OSError:  # a file system without hard links: checked just now
                os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return out


def _head(path: Path) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read(16)
    except OSError:
        return b""
