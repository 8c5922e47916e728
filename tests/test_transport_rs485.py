"""Rs485Transport through pyserial on a real pseudo-terminal, against scripted drives on the master side."""

from __future__ import annotations

import contextlib
import os
import select
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import pytest

from motion.errors import EncodeError, PortHeld, PortLost, TransportError
from motion.protocol import (
    Bare,
    Command,
    Message,
    MotorState,
    MultiMotorTorque,
    MultiTurnPositionSpeed,
    Rs485Parser,
    Status1,
    rs485_frame,
)
from motion.protocol.table import RS485_MAX_DATA_BYTES, ProtocolFamily
from motion.transport import Request, Rs485Transport, open_transport
from tests.junk_flood import JunkFlood
from tests.test_transport_peers import MARGIN_S, LateHost, Script, ScriptedDrives, assert_balanced, status2, tag_of


class PtyDrives(ScriptedDrives[bytes]):
    """Scripted drives on the master side of a pseudo-terminal."""

    def __init__(self, master_fd: int, scripts: dict[int, Script[bytes]] | None = None) -> None:
        super().__init__(scripts)
        self.fd = master_fd
        self.parser = Rs485Parser()

    def poll(self, timeout_s: float) -> Iterable[tuple[int | None, Message]]:
        if not select.select([self.fd], [], [], timeout_s)[0]:
            return ()
        self.parser.feed(os.read(self.fd, 256))
        found: list[tuple[int | None, Message]] = []
        while (frame := self.parser.next_frame()) is not None:
            found.append(rs485_frame.decode_request(frame.to_bytes()))
        return found

    def encode(self, message: Message, motor_id: int) -> bytes:
        return rs485_frame.encode_reply(message, motor_id)

    def send(self, payload: bytes) -> None:
        os.write(self.fd, payload)


class Pty:
    """A pseudo-terminal pair; the transport opens ``path`` (the slave), the drives use ``master``."""

    def __init__(self) -> None:
        self.master, self._slave = os.openpty()
        self.path = os.ttyname(self._slave)

    def close_master(self) -> None:
        if self.master >= 0:
            os.close(self.master)
            self.master = -1

    def close(self) -> None:
        self.close_master()
        os.close(self._slave)


@pytest.fixture
def pty() -> Iterator[Pty]:
    pair = Pty()
    yield pair
    pair.close()


@contextlib.contextmanager
def rig(
    pty: Pty, scripts: dict[int, Script[bytes]] | None = None, **kwargs: Any
) -> Iterator[tuple[Rs485Transport, PtyDrives]]:
    # The transport opens first: pyserial puts the line in raw mode (no echo) before a drive writes to it.
    with Rs485Transport(pty.path, **kwargs) as transport:
        drives = PtyDrives(pty.master, scripts)
        drives.start()
        try:
            yield transport, drives
        finally:
            drives.stop()


def test_request_reply_for_several_motors(pty: Pty) -> None:
    requests = [
        Request(1, MultiTurnPositionSpeed(angle_deg=90.0, max_speed_dps=360.0)),
        Request(2, Bare(Command.READ_STATUS_1)),
        status2(3),
        status2(1),
    ]
    with rig(pty) as (transport, drives):
        for cycle in (1, 2):
            start = transport.clock()
            replies = transport.transact(requests, start + 0.5)
            assert transport.clock() < start + 0.5  # returned as soon as the last reply was in
            assert [r.motor_id for r in replies] == [1, 2, 3, 1]
            assert all(r.ok for r in replies)
            assert isinstance(replies[0].message, MotorState)
            assert replies[0].message.command is Command.MULTI_TURN_POSITION_SPEED
            assert isinstance(replies[1].message, Status1)
            assert [tag_of(r.message) for r in replies] == [cycle] * 4
        assert drives.requests == [(r.motor_id, r.message) for r in requests] * 2  # sent in order
        assert transport.counters[1].replied == 4
        assert transport.bus_counters.dropped_bytes == 0
        assert_balanced(transport)


def test_garbage_before_a_reply_is_dropped_and_counted(pty: Pty) -> None:
    scripts: dict[int, Script[bytes]] = {
        1: Script(edit=lambda raw: [b"\x00\x11\x22" + raw]),  # line noise
        2: Script(edit=lambda raw: [b"\x3e\x01\x02" + raw]),  # a false start of frame
    }
    with rig(pty, scripts) as (transport, _):
        replies = transport.transact([status2(1), status2(2), status2(3)], transport.clock() + 0.5)
        assert all(r.ok for r in replies)
        assert [transport.counters[m].bad_frames for m in (1, 2, 3)] == [1, 1, 0]
        assert transport.bus_counters.dropped_bytes == 6


def test_bad_checksum_is_a_bad_frame_and_no_reply(pty: Pty) -> None:
    def flip_data_checksum(raw: bytes) -> list[bytes]:
        return [raw[:-1] + bytes([raw[-1] ^ 0x5A])]

    with rig(pty, {2: Script(edit=flip_data_checksum)}) as (transport, _):
        deadline = transport.clock() + 0.15
        replies = transport.transact([status2(1), status2(2), status2(3)], deadline)
        assert transport.clock() <= deadline + MARGIN_S
        assert [r.ok for r in replies] == [True, False, True]
        assert transport.counters[2].bad_frames == 1
        assert transport.counters[2].timeouts == 1


def test_truncated_reply_is_given_up_at_the_window_end(pty: Pty) -> None:
    with rig(pty, {1: Script(edit=lambda raw: [raw[:7]])}) as (transport, _):
        deadline = transport.clock() + 0.1
        replies = transport.transact([status2(1), status2(2)], deadline)
        assert transport.clock() <= deadline + MARGIN_S
        assert [r.ok for r in replies] == [False, True]
        assert transport.counters[1].bad_frames == 1
        assert transport.counters[2].bad_frames == 0


def test_silent_motor_costs_only_its_share_of_the_time(pty: Pty) -> None:
    # Three requests and 150 ms: the silent first motor gets a third (50 ms), the others answer at once.
    with rig(pty, {1: Script(silent=True)}) as (transport, _):
        start = transport.clock()
        deadline = start + 0.15
        replies = transport.transact([status2(1), status2(2), status2(3)], deadline)
        elapsed = transport.clock() - start
        assert [r.ok for r in replies] == [False, True, True]
        assert replies[0].message is None and replies[0].received_s is None
        assert 0.05 <= elapsed < 0.15
        assert transport.counters[1].timeouts == 1
        assert_balanced(transport)


def test_late_reply_to_the_previous_request_of_the_cycle_is_stale(pty: Pty) -> None:
    # Motor 1's window is 100 ms; its reply comes at 120 ms, in motor 2's window (motor 2 answers at ~150 ms).
    with rig(pty, {1: Script(delays_s=[0.12]), 2: Script(delays_s=[0.05])}) as (transport, _):
        replies = transport.transact([status2(1), status2(2)], transport.clock() + 0.2)
        assert [r.ok for r in replies] == [False, True]
        assert transport.counters[1].stale_frames == 1
        replies = transport.transact([status2(1), status2(2)], transport.clock() + 0.5)
        assert [tag_of(r.message) for r in replies] == [2, 2]
        assert_balanced(transport)


def test_late_reply_from_the_previous_cycle_is_stale_not_matched(pty: Pty) -> None:
    # The reply to cycle 1 comes during cycle 2, after cycle 2's request went out and before its answer.
    with rig(pty, {1: Script(delays_s=[0.08])}) as (transport, _):
        assert not transport.transact([status2(1)], transport.clock() + 0.03)[0].ok
        (reply,) = transport.transact([status2(1)], transport.clock() + 0.5)
        assert reply.ok and tag_of(reply.message) == 2
        c = transport.counters[1]
        assert (c.sent, c.replied, c.timeouts, c.stale_frames) == (2, 1, 1, 1)


def test_duplicate_reply_is_stale(pty: Pty) -> None:
    # Both copies in one write: a copy that came after the next request went out could not be told from its answer.
    with rig(pty, {1: Script(edit=lambda raw: [raw + raw])}) as (transport, _):
        for cycle in (1, 2, 3):
            (reply,) = transport.transact([status2(1)], transport.clock() + 0.5)
            assert reply.ok and tag_of(reply.message) == cycle
        assert transport.counters[1].stale_frames == 3
        assert transport.counters[1].replied == 3
        assert transport.bus_counters.bad_frames == 0


def test_a_reply_that_came_while_the_host_was_descheduled_is_taken_not_missed(pty: Pty) -> None:
    # The first request goes out, the host sleeps past the deadline while drive 1 answers: its reply is in the port
    # when the host looks again, an answer in time (the host was late, not the drive); the second request's turn came
    # after the deadline, so it is not sent (and is no reply). Before: both counted as missed replies.
    late = LateHost()
    with rig(pty, clock=late.clock) as (transport, drives):
        transport.frame_tap = late.tap
        replies = transport.transact([status2(1), status2(2)], late.clock() + 0.5)
        assert [r.ok for r in replies] == [True, False]
        assert tag_of(replies[0].message) == 1
        assert (transport.counters[1].replied, transport.counters[1].timeouts) == (1, 0)
        assert transport.bus_counters.skipped_requests == 1
        assert drives.requests == [(1, status2(1).message)]
        assert_balanced(transport)


def test_requests_after_the_deadline_are_not_sent(pty: Pty) -> None:
    with rig(pty) as (transport, drives):
        replies = transport.transact([status2(1), status2(2)], transport.clock() - 0.001)
        assert [r.ok for r in replies] == [False, False]
        assert transport.bus_counters.skipped_requests == 2
        assert transport.counters[1].sent == 0 and transport.counters[1].timeouts == 1
        assert drives.requests == []
        assert_balanced(transport)


def test_invalid_baudrate_names_the_valid_set(pty: Pty) -> None:
    with pytest.raises(EncodeError, match="9600, 19200, 57600, 115200"):
        Rs485Transport(pty.path, 38400)
    with pytest.raises(EncodeError, match="baudrate"):
        open_transport("rs485", pty.path, baudrate=0)
    with open_transport("rs485", pty.path, baudrate=9600) as transport:
        assert isinstance(transport, Rs485Transport)


def test_multi_motor_torque_cannot_be_broadcast_on_rs485(pty: Pty) -> None:
    with rig(pty) as (transport, drives):
        with pytest.raises(EncodeError, match="0x280"):
            transport.transact([status2(1), Request(1, MultiMotorTorque(0.0, 0.0, 0.0, 0.0))], transport.clock() + 0.1)
        assert drives.requests == []  # nothing went out


def test_close_releases_the_port_also_after_an_error(pty: Pty) -> None:
    with Rs485Transport(pty.path) as transport, pytest.raises(TransportError, match="lock"):
        Rs485Transport(pty.path)  # the port is taken
    with pytest.raises(EncodeError), Rs485Transport(pty.path) as transport:
        transport.transact([status2(99)], transport.clock() + 0.1)
    assert transport.closed
    transport.close()  # twice is fine
    with pytest.raises(TransportError, match="closed"):
        transport.transact([status2(1)], transport.clock() + 0.1)
    with rig(pty) as (again, _):  # the lock was released
        assert again.transact([status2(1)], again.clock() + 0.5)[0].ok


def test_port_gone_is_lost_for_good_and_closes_clean(pty: Pty) -> None:
    with rig(pty) as (transport, drives):
        assert transport.transact([status2(1)], transport.clock() + 0.5)[0].ok
        drives.stop()
        pty.close_master()  # the other end disappears (the slave hangs up: reads end, writes fail with EIO)
        with pytest.raises(PortLost, match="rs485.*the port is gone"):
            transport.transact([status2(1)], transport.clock() + 0.1)
        assert transport.lost is not None and transport.closed  # nothing more can be sent: a loop on it ends
        with pytest.raises(PortLost, match="the port is gone"):  # again at once, without trying the port
            transport.transact([status2(1)], transport.clock() + 0.1)
        serial_port = transport._serial
    assert transport.closed and not serial_port.is_open  # the exit closed it without raising
    assert transport.lost is not None


def test_a_line_flooded_with_junk_keeps_the_deadline_and_counts_the_junk() -> None:
    with JunkFlood(6.0) as flood, Rs485Transport(flood.path) as transport:
        start = transport.clock()
        replies = transport.transact([status2(1), status2(2)], start + 0.2)
        assert transport.clock() - start < 0.2 + 2.0  # the flood lasts 6 s: a drain that ignored the time would too
        assert [r.ok for r in replies] == [False, False]
        assert transport._parser.pending <= rs485_frame.frame_size(RS485_MAX_DATA_BYTES)  # junk is dropped as it comes
        assert transport.bus_counters.dropped_bytes > 0
        assert "bytes of junk" in transport.junk_note()


def test_opening_a_missing_port_raises_transport_error(tmp_path: Any) -> None:
    with pytest.raises(TransportError, match="cannot open RS485 port"):
        Rs485Transport(str(tmp_path / "no-such-port"))


def test_a_port_a_session_holds_is_refused_to_a_second_one_by_its_resolved_path(pty: Pty, tmp_path: Path) -> None:
    # the session's lock is keyed by the device the path resolves to: a symlink to the port is the same port
    link = tmp_path / "link"
    link.symlink_to(pty.path)
    with rig(pty) as (first, drives):
        with pytest.raises(PortHeld, match="held by another rmd-motion session") as refused:
            Rs485Transport(str(link))
        assert f"RS485 port {str(link)!r}" in str(refused.value) and f"process {os.getpid()}" in str(refused.value)
        assert refused.value.link == "rs485"
        assert drives.requests == []  # nothing went out from the second opener
        # the first session goes on, and the drives' side of the pty (the master, the emulator's) is never locked out
        assert first.transact([status2(1)], first.clock() + 0.5)[0].ok
        siblings = first.with_family(ProtocolFamily.V3)  # the port's lock goes with the port to its new owner
        first.close()
        with pytest.raises(PortHeld):
            Rs485Transport(pty.path)
        siblings.close()
    with Rs485Transport(str(link)) as again:  # released with the port
        assert not again.closed
