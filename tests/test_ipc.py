"""The loop <-> sidecar pipes: framing, atomic <= PIPE_BUF writes, drop-don't-block."""

from __future__ import annotations

import os
import threading

import numpy as np
import pytest

from mrrig.loop.samples import FIELDS, SAMPLE_DTYPE
from mrrig.rigio.ipc import (
    FORCE_REF,
    HEADER,
    PIPE_BUF,
    SAMPLES_PER_MESSAGE,
    LoopEnd,
    Msg,
    SidecarEnd,
    decode_json,
    decode_samples,
    make_channel,
)


def _samples(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    arr = np.zeros(n, SAMPLE_DTYPE)
    for name in FIELDS:
        if SAMPLE_DTYPE[name].kind == "f":
            arr[name] = rng.normal(size=n) * 100.0
        else:
            arr[name] = rng.integers(0, 3 if name == "state" else 256, size=n)
    arr["t"] = np.arange(n) * 0.002
    return arr


@pytest.fixture
def ends():
    fds = make_channel(pipe_bytes=None)
    loop = LoopEnd(fds.loop_rx, fds.loop_tx)
    side = SidecarEnd(fds.sidecar_rx, fds.sidecar_tx)
    yield loop, side
    loop.close()
    side.close()


def _read_all(side: SidecarEnd) -> list[tuple[int, bytes]]:
    out = []
    while True:
        got = side.read(timeout_s=0.05)
        if not got:
            return out
        out += got


def test_samples_roundtrip_bit_for_bit(ends):
    loop, side = ends
    arr = _samples(100)
    assert loop.send_samples(arr)
    msgs = _read_all(side)
    assert {m for m, _ in msgs} == {Msg.SAMPLES}
    back = np.concatenate([decode_samples(p) for _, p in msgs])
    assert back.tobytes() == arr.tobytes()
    assert loop.dropped == 0


def test_sample_batches_are_split_into_messages_of_at_most_pipe_buf(ends):
    loop, side = ends
    n = 3 * SAMPLES_PER_MESSAGE + 7
    loop.send_samples(_samples(n))
    msgs = _read_all(side)
    sizes = [len(p) // SAMPLE_DTYPE.itemsize for _, p in msgs]
    assert sizes == [SAMPLES_PER_MESSAGE] * 3 + [7]
    assert all(HEADER.size + len(p) <= PIPE_BUF for _, p in msgs)
    # as full as PIPE_BUF allows: one more sample would not fit
    assert HEADER.size + (SAMPLES_PER_MESSAGE + 1) * SAMPLE_DTYPE.itemsize > PIPE_BUF


def test_json_messages_roundtrip_with_their_types(ends):
    loop, side = ends
    event = {"t": 1.25, "level": "error", "text": "bad CRC", "kind": "fault"}
    status = {"state": "ARMED", "counters": {"frames": 12}}
    reply = {"id": 7, "ok": True}
    summary = {"et": 0.031, "faults": []}
    loop.send_event(event)
    loop.send_status(status)
    replies = loop.reply_writer()  # the control thread's own writer on the same pipe
    replies.send_reply(reply)
    replies.close()
    loop.send_summary(summary)
    loop.send_stop()
    msgs = _read_all(side)
    assert [m for m, _ in msgs] == [Msg.EVENT, Msg.STATUS, Msg.REPLY, Msg.SUMMARY, Msg.STOP]
    assert [decode_json(p) for _, p in msgs[:4]] == [event, status, reply, summary]
    assert msgs[4][1] == b""


def test_requests_and_force_refs_reach_the_loop_decoded(ends):
    loop, side = ends
    assert loop.poll() == []
    side.send_request(3, b'{"cmd": "arm"}')
    side.send_force_ref(-512.5, 123.0)
    side.send_heartbeat()
    assert loop.poll() == [
        (Msg.REQUEST, (3, b'{"cmd": "arm"}')),  # the JSON is decoded by the control thread
        (Msg.FORCE_REF, (-512.5, 123.0)),
        (Msg.HEARTBEAT, None),
    ]


def test_loop_poll_buffers_a_partial_frame_until_it_completes():
    fds = make_channel(pipe_bytes=None)
    loop = LoopEnd(fds.loop_rx, fds.loop_tx)
    try:
        frame = HEADER.pack(Msg.FORCE_REF, FORCE_REF.size) + FORCE_REF.pack(42.0, 1.5)
        os.write(fds.sidecar_tx, frame[:5])
        assert loop.poll() == []
        os.write(fds.sidecar_tx, frame[5:])
        assert loop.poll() == [(Msg.FORCE_REF, (42.0, 1.5))]
    finally:
        loop.close()
        os.close(fds.sidecar_rx)
        os.close(fds.sidecar_tx)


def test_full_pipe_drops_and_counts_instead_of_blocking(ends):
    loop, side = ends
    arr = _samples(SAMPLES_PER_MESSAGE)
    attempts = 2000  # 8 MB: far more than any pipe holds
    results: list[bool] = []
    sender = threading.Thread(
        target=lambda: results.extend(loop.send_samples(arr) for _ in range(attempts)), daemon=True
    )
    sender.start()
    sender.join(timeout=20)
    assert not sender.is_alive(), "send_samples blocked on a full pipe"
    assert loop.dropped == results.count(False) > 0
    assert loop.dropped_samples == loop.dropped * SAMPLES_PER_MESSAGE
    msgs = _read_all(side)
    # every message that went in came out whole: no partial writes
    assert len(msgs) == attempts - loop.dropped
    assert all(p == arr.tobytes() for _, p in msgs)


def test_a_summary_with_more_faults_than_a_message_holds_lists_the_first_and_counts_the_rest(
    ends,
):
    loop, side = ends
    faults = [
        {"t": 0.01 * k, "reason": f"no sensor frame for {20 + k % 7}.1 ms"} for k in range(300)
    ]
    assert loop.send_summary({"et": 0.02, "faults": faults})
    [(mtype, payload)] = _read_all(side)
    got = decode_json(payload)
    assert mtype == Msg.SUMMARY and got["et"] == 0.02
    assert 0 < len(got["faults"]) < 300 and got["faults"] == faults[: len(got["faults"])]
    assert got["faults_not_listed"] == 300 - len(got["faults"])
    assert loop.dropped == 0


def test_oversize_json_is_dropped_and_counted_not_raised(ends):
    loop, side = ends
    assert not loop.send_event({"text": "x" * PIPE_BUF})
    assert loop.dropped == 1
    assert _read_all(side) == []


def test_loop_end_sees_a_dead_sidecar_without_raising():
    fds = make_channel(pipe_bytes=None)
    loop = LoopEnd(fds.loop_rx, fds.loop_tx)
    try:
        os.close(fds.sidecar_rx)
        os.close(fds.sidecar_tx)
        assert loop.poll() == []
        assert not loop.send_samples(_samples(3))
        assert loop.closed
        assert loop.dropped == 1
    finally:
        loop.close()


def test_a_summary_with_more_stalls_than_a_message_holds_lists_the_largest_and_counts_all(ends):
    """The daemon's summary lists up to 256 of its loop's stalls (about 18 kB); the recording's
    message holds 4 kB: the largest are listed, the rest counted, the faults kept."""
    loop, side = ends
    windows = [[0.002 * k, 0.002 * k + 0.004, 2.0 + (k * 37) % 50 / 10.0, 0.0] for k in range(256)]
    stalls = {"measured": True, "windows_count": 300, "windows": windows, "windows_not_listed": 44}
    faults = [{"t": 1.0, "reason": "no sensor frame for 20.5 ms"}]
    assert loop.send_summary({"et": 0.02, "faults": faults, "kernel_stalls": stalls})
    [(mtype, payload)] = _read_all(side)
    got = decode_json(payload)
    assert mtype == Msg.SUMMARY and got["faults"] == faults
    listed = got["kernel_stalls"]["windows"]
    assert 0 < len(listed) < 256 and got["kernel_stalls"]["windows_not_listed"] == 300 - len(listed)
    assert listed == sorted(listed)  # by time
    smallest_listed = min(w[2] for w in listed)
    assert all(w in listed for w in windows if w[2] > smallest_listed)
