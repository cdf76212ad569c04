"""python-can, imported without asammdf: `from mrrig.pycan import can`.

python-can imports asammdf at `import can` where it is installed (for its MF4 bus logs), and
asammdf imports pandas: 134 MB more in every process that touches a bus (27 MB with it
hidden, 161 MB without), the rig daemon's locked loop among them, and pandas' numexpr logging
a line at start. asammdf is hidden while python-can is first imported; `with_mf4()` brings
python-can's MF4 reader and writer to life where a bus log in that format is read or written
(the sidecar, `mrrig review --can-log`).
"""

from __future__ import annotations

import importlib
import sys

_hide = "can" not in sys.modules and "asammdf" not in sys.modules
if _hide:
    sys.modules["asammdf"] = None  # type: ignore[assignment]  # import of it fails, as absent
try:
    import can
finally:
    if _hide:
        del sys.modules["asammdf"]


def with_mf4() -> None:
    """python-can's MF4 reader and writer with asammdf, where it is installed: its module is
    executed again in place (the classes python-can's Logger and LogReader hold keep it as
    their globals, so they see asammdf after this)."""
    from can.io import mf4

    if mf4.asammdf is None and importlib.util.find_spec("asammdf") is not None:
        importlib.reload(mf4)


__all__ = ["can", "with_mf4"]
