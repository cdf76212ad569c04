"""A recording's writer process ended by SIGTERM: with the close handler the recording is complete;
without it, what reached the disk reads back as a clean prefix and verify names the missing end
marker (a process module: the recording's other checks are tests/test_recording.py's, which hold
the machine shared)."""

from __future__ import annotations

import signal
from pathlib import Path

import numpy as np
import pytest

from mrrig.offline.review import ReviewError, read_recording, verify_rrd
from tests.test_recording import _start_writer


@pytest.mark.process
def test_sigterm_with_close_handler_leaves_a_complete_recording(tmp_path: Path) -> None:
    path = tmp_path / "term.rrd"
    proc = _start_writer(path, "handled")
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0
    handed = int(out.split()[-1])
    verify_rrd(path)
    back = read_recording(path)
    assert back.samples.size == handed  # the buffer was flushed by close()
    np.testing.assert_array_equal(back.samples["t"], np.arange(handed) * 0.002)


@pytest.mark.process
def test_unhandled_sigterm_leaves_a_recording_without_end_marker(tmp_path: Path) -> None:
    """No end marker (which `close()` writes), so verify fails; what reached the disk still
    reads back as a clean prefix, less the recorder's buffer and rerun's batcher (up to about
    one flush interval)."""
    path = tmp_path / "killed.rrd"
    proc = _start_writer(path, "unhandled")
    proc.send_signal(signal.SIGTERM)
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGTERM
    with pytest.raises(ReviewError, match="killed.rrd: truncated: no end marker"):
        verify_rrd(path)
    back = read_recording(path)
    np.testing.assert_array_equal(back.samples["t"], np.arange(back.samples.size) * 0.002)
