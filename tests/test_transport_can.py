"""CanTransport on python-can's real ``virtual`` interface, against scripted drives on the same channel."""

from __future__ import annotations

import contextlib
import itertools
import os
import select
import subprocess
import sys
import time
import uuid
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import can.interfaces.virtual
import pytest

from motion.errors import EncodeError, PortHeld, TransportError
from motion.protocol import (
    Bare,
    CanFrame,
    Command,
    Message,
    MotorState,
    MultiMotorTorque,
    MultiTurnPositionSpeed,
    SpeedControl,
    Status1,
    TorqueControl,
    can_frame,
)
from motion.protocol.table import ProtocolFamily
from motion.transport import CanTransport, Request, open_transport
from motion.transport.can_endpoint import CanEndpoint
from tests.test_transport_peers import MARGIN_S, LateHost, Script, ScriptedDrives, assert_balanced, status2, tag_of

ROOT = Path(__file__).resolve().parent.parent


class CanDrives(ScriptedDrives[CanFrame]):
    """Scripted drives on a virtual CAN channel."""

    def __init__(self, channel: str, scripts: dict[int, Script[CanFrame]] | None = None) -> None:
        super().__init__(scripts)
        self.endpoint = CanEndpoint("virtual", channel)

    def poll(self, timeout_s: float) -> Iterable[tuple[int | None, Message]]:
        received = self.endpoint.recv(timeout_s)
        if received is None:
            return ()
        request = can_frame.decode_request(received[0].arbitration_id, received[0].data)
        return ((request.motor_id, request.message),)

    def encode(self, message: Message, motor_id: int) -> CanFrame:
        return can_frame.encode_reply(message, motor_id)

    def send(self, payload: CanFrame) -> None:
        self.endpoint.send(payload)

    def stop(self) -> None:
        try:
            super().stop()
        finally:
            self.endpoint.close()


@pytest.fixture
def channel() -> str:
    return f"rmd-test-{uuid.uuid4().hex}"


@contextlib.contextmanager
def rig(
    channel: str, scripts: dict[int, Script[CanFrame]] | None = None, **kwargs: Any
) -> Iterator[tuple[CanTransport, CanDrives]]:
    drives = CanDrives(channel, scripts)
    drives.start()
    try:
        with CanTransport("virtual", channel, **kwargs) as transport:
            yield transport, drives
    finally:
        drives.stop()


def test_replies_are_matched_by_motor_and_command_in_any_order(channel: str) -> None:
    # Motor 1 answers 30 ms late, so its two replies arrive after those of motors 2 and 3.
    with rig(channel, {1: Script(delays_s=[0.03])}) as (transport, _):
        requests = [
            status2(1),
            Request(2, MultiTurnPositionSpeed(angle_deg=90.0, max_speed_dps=360.0)),
            Request(1, Bare(Command.READ_STATUS_1)),
            Request(3, SpeedControl(speed_dps=10.0)),
        ]
        start = transport.clock()
        replies = transport.transact(requests, start + 0.5)
        end = transport.clock()
    assert [r.motor_id for r in replies] == [1, 2, 1, 3]
    assert [r.request for r in replies] == [r.message for r in requests]
    assert all(r.ok for r in replies)
    assert isinstance(replies[0].message, MotorState) and replies[0].message.command is Command.READ_STATUS_2
    assert isinstance(replies[1].message, MotorState)
    assert replies[1].message.command is Command.MULTI_TURN_POSITION_SPEED
    assert isinstance(replies[2].message, Status1)
    assert isinstance(replies[3].message, MotorState) and replies[3].message.command is Command.SPEED
    assert [tag_of(r.message) for r in replies] == [1, 1, 1, 1]
    times = [r.received_s for r in replies]
    assert all(t is not None and start <= t <= end for t in times)
    assert times[1] is not None and times[0] is not None and times[1] < times[0]  # really out of order
    assert end < start + 0.5  # returned as soon as everything was in
    assert transport.counters[1].replied == 2
    assert transport.bus_counters.cycles == 1


def test_a_transport_over_an_injected_port_uses_it_and_closes_it(channel: str) -> None:
    drives = CanDrives(channel)
    drives.start()
    try:
        port = CanEndpoint("virtual", channel)
        with CanTransport.over(port) as transport:
            assert transport.port is port and transport.describe() == f"can virtual:{channel}"
            replies = transport.transact([status2(1), status2(2)], transport.clock() + 0.5)
            assert [r.motor_id for r in replies] == [1, 2] and all(r.ok for r in replies)
        with pytest.raises(TransportError):  # closing the transport released the injected port
            port.send(CanFrame(0x141, bytes(8)), 0.1)
    finally:
        drives.stop()


def test_missing_reply_is_reported_explicitly_by_the_deadline(channel: str) -> None:
    with rig(channel, {2: Script(silent=True)}) as (transport, _):
        start = transport.clock()
        deadline = start + 0.05
        replies = transport.transact([status2(1), status2(2), status2(3)], deadline)
        end = transport.clock()
        assert deadline <= end <= deadline + MARGIN_S
        assert [r.ok for r in replies] == [True, False, True]
        assert replies[1].motor_id == 2 and replies[1].message is None and replies[1].received_s is None
        assert transport.counters[2].timeouts == 1 and transport.counters[2].replied == 0
        assert_balanced(transport)


def test_replies_that_came_while_the_host_was_descheduled_are_taken_not_missed(channel: str) -> None:
    # After each request the host sleeps past the deadline while the drive answers: the replies are in the receive
    # queue when it looks again, answers in time (the host was late, not the drives). Before: all three missed.
    late = LateHost()
    with rig(channel, clock=late.clock) as (transport, _):
        transport.frame_tap = late.tap
        replies = transport.transact([status2(1), status2(2), status2(3)], late.clock() + 0.5)
        assert [r.ok for r in replies] == [True, True, True]
        assert [tag_of(r.message) for r in replies] == [1, 1, 1]
        assert all(c.timeouts == 0 for c in transport.counters.values())
        assert_balanced(transport)


def test_late_reply_arriving_during_the_next_cycle_is_stale_not_matched(channel: str) -> None:
    # Motor 1's first reply comes 300 ms late: after cycle 1's deadline (30 ms, with room for a host that keeps the
    # test waiting a while), in the middle of cycle 2.
    with rig(channel, {1: Script(delays_s=[0.3])}) as (transport, _):
        first = transport.transact([status2(1), status2(2)], transport.clock() + 0.03)
        assert [r.ok for r in first] == [False, True]
        second = transport.transact([status2(1), status2(2)], transport.clock() + 1.0)
        assert [r.ok for r in second] == [True, True]
        assert [tag_of(r.message) for r in second] == [2, 2]  # the answer to cycle 2, not the late one
        c = transport.counters[1]
        assert (c.sent, c.replied, c.timeouts, c.stale_frames) == (2, 1, 1, 1)
        assert transport.counters[2].stale_frames == 0
        assert_balanced(transport)


def test_late_reply_arriving_between_cycles_is_drained_as_stale(channel: str) -> None:
    # The reply comes 0.2 s after a 20 ms deadline: late on a host descheduled for a while too (a 40 ms delay was
    # taken in on time under ../shared/tools/slow-host, where the transact itself returned 20 ms late).
    with rig(channel, {1: Script(delays_s=[0.2])}) as (transport, _):
        assert not transport.transact([status2(1)], transport.clock() + 0.02)[0].ok
        time.sleep(0.4)  # the late reply is now waiting in the receive queue
        (reply,) = transport.transact([status2(1)], transport.clock() + 0.5)
        assert reply.ok and tag_of(reply.message) == 2
        assert transport.counters[1].stale_frames == 1
        # The mark is used up: the next cycles match normally.
        (reply,) = transport.transact([status2(1)], transport.clock() + 0.5)
        assert reply.ok and tag_of(reply.message) == 3
        assert_balanced(transport)


def test_after_a_generation_probe_the_next_answer_counts(channel: str) -> None:
    # scan's second try under a busy host: the late answers to its first status reads were read by the generation
    # probe (the port, behind the slots), and their outstanding marks then swallowed the drives' real answers: every
    # drive that had answered late once was reported missing
    with rig(channel, {1: Script(delays_s=[0.2])}) as (transport, _):
        assert not transport.transact([Request(1, Bare(Command.READ_STATUS_1))], transport.clock() + 0.02)[0].ok
        time.sleep(0.4)  # the late reply (tag 1) is now waiting in the receive queue
        assert transport.probe_families([1], 0.5) == {1: ProtocolFamily.V2}  # drains it, takes the probe's (tag 2)
        (reply,) = transport.transact([Request(1, Bare(Command.READ_STATUS_1))], transport.clock() + 0.5)
        assert reply.ok and tag_of(reply.message) == 3
        assert transport.counters[1].stale_frames == 0


def test_lost_reply_costs_at_most_one_more_cycle(channel: str) -> None:
    # The reply to the first request is lost: the next reply is taken for the late one (the documented
    # one-reply ambiguity), and from the third cycle on everything matches again.
    replies = itertools.count()

    def lose_first(frame: CanFrame) -> list[CanFrame]:
        return [] if next(replies) == 0 else [frame]

    with rig(channel, {1: Script(edit=lose_first)}) as (transport, _):
        oks = [transport.transact([status2(1)], transport.clock() + 0.05)[0].ok for _ in range(4)]
        assert oks == [False, False, True, True]
        c = transport.counters[1]
        assert (c.replied, c.timeouts, c.stale_frames) == (2, 2, 1)


def test_duplicate_reply_is_stale(channel: str) -> None:
    # The pause lets each second copy arrive before the next cycle's request: one that came after it could not
    # be told from the answer to it.
    with rig(channel, {1: Script(edit=lambda f: [f, f])}) as (transport, _):
        for cycle in (1, 2):
            (reply,) = transport.transact([status2(1)], transport.clock() + 0.2)
            assert reply.ok and tag_of(reply.message) == cycle
            time.sleep(0.02)
        transport.transact([], transport.clock() + 0.01)  # takes in the second copy of cycle 2's reply
        assert transport.counters[1].stale_frames == 2
        assert transport.counters[1].replied == 2


def corrupt_then_good(frame: CanFrame) -> list[CanFrame]:
    return [
        CanFrame(frame.arbitration_id, b"\xee" + frame.data[1:]),  # unknown command byte
        CanFrame(frame.arbitration_id, frame.data[:5]),  # short frame
        frame,
    ]


def test_corrupt_frames_are_counted_bad_and_the_good_reply_still_matched(channel: str) -> None:
    with rig(channel, {2: Script(edit=corrupt_then_good)}) as (transport, _):
        replies = transport.transact([status2(1), status2(2)], transport.clock() + 0.2)
        assert [r.ok for r in replies] == [True, True]
        assert transport.counters[2].bad_frames == 2
        assert transport.counters[1].bad_frames == 0


def test_frames_on_wrong_ids_are_never_matched(channel: str) -> None:
    def elsewhere(frame: CanFrame) -> list[CanFrame]:
        return [CanFrame(0x147, frame.data), CanFrame(0x300, frame.data), CanFrame(0x280, frame.data)]

    with rig(channel, {2: Script(edit=elsewhere)}) as (transport, _):
        replies = transport.transact([status2(1), status2(2)], transport.clock() + 0.05)
        assert [r.ok for r in replies] == [True, False]
        assert transport.counters[7].stale_frames == 1
        assert transport.bus_counters.unknown_id_frames == 2
        assert_balanced(transport)


def test_multi_motor_torque_yields_four_replies_in_its_place(channel: str) -> None:
    torque = MultiMotorTorque(iq1_a=1.6, iq2_a=-0.8, iq3_a=0.48, iq4_a=0.0)  # whole 0.016 A steps
    with rig(channel, {3: Script(silent=True)}) as (transport, drives):
        replies = transport.transact([Request(0, torque), status2(5)], transport.clock() + 0.05)
        assert [r.motor_id for r in replies] == [1, 2, 3, 4, 5]
        assert [r.ok for r in replies] == [True, True, False, True, True]
        assert all(r.request == torque for r in replies[:4])
        answered = [r.message for r in replies[:4] if r.ok]
        assert all(isinstance(m, MotorState) and m.command is Command.TORQUE for m in answered)
        assert drives.requests[0] == (None, torque)
        assert [transport.counters[m].sent for m in (1, 2, 3, 4, 5)] == [1, 1, 1, 1, 1]
        assert transport.counters[3].timeouts == 1
        assert_balanced(transport)


def test_same_motor_and_command_twice_in_a_cycle_is_first_in_first_out(channel: str) -> None:
    torque = MultiMotorTorque(iq1_a=0.16, iq2_a=0.0, iq3_a=0.0, iq4_a=0.0)
    with rig(channel) as (transport, _):
        requests = [status2(1), Request(0, torque), status2(1), Request(1, TorqueControl(iq_a=0.32))]
        replies = transport.transact(requests, transport.clock() + 0.2)
        assert [r.motor_id for r in replies] == [1, 1, 2, 3, 4, 1, 1]
        assert [tag_of(r.message) for r in replies] == [1, 1, 1, 1, 1, 2, 2]
        assert replies[6].request == TorqueControl(iq_a=0.32)
        assert_balanced(transport)


def test_injected_clock_sets_the_time_base(channel: str) -> None:
    offset_s = 1000.0

    def clock() -> float:
        return time.monotonic() + offset_s

    with rig(channel, clock=clock) as (transport, _):
        deadline = clock() + 0.2
        (reply,) = transport.transact([status2(4)], deadline)
        assert reply.ok and reply.received_s is not None
        assert offset_s < reply.received_s <= deadline


def test_opening_a_bad_interface_raises_transport_error() -> None:
    with pytest.raises(TransportError, match="no-such-interface"):
        CanTransport("no-such-interface", "x")
    with pytest.raises(TransportError, match="no-such-interface"):
        open_transport("can", "no-such-interface", "x")
    with pytest.raises(TransportError, match="valid: can, rs485"):
        open_transport("carrier-pigeon")


def test_send_failure_surfaces_as_transport_error(channel: str) -> None:
    # A peer whose one-frame receive queue is never read makes the second send time out: a real write failure.
    with (
        CanEndpoint("virtual", channel, rx_queue_size=1),
        CanTransport("virtual", channel) as transport,
        pytest.raises(TransportError, match="send"),
    ):
        transport.transact([status2(1), status2(2)], transport.clock() + 0.02)
    assert transport.closed


def test_close_releases_the_bus_also_after_an_error(channel: str) -> None:
    with rig(channel) as (transport, _), pytest.raises(EncodeError):
        transport.transact([status2(33)], transport.clock() + 0.05)
    assert transport.closed
    assert channel not in can.interfaces.virtual.channels  # both ends shut down: python-can forgot the channel
    transport.close()  # twice is fine
    with pytest.raises(TransportError, match="closed"):
        transport.transact([status2(1)], transport.clock() + 0.05)
    with rig(channel) as (again, _):
        assert again.transact([status2(1)], again.clock() + 0.2)[0].ok


def test_a_transport_another_package_declares_is_found_by_its_entry_point(tmp_path: Path) -> None:
    # an installed distribution (its dist-info on the path) declares a kind of link in the group; the registry opens it
    # by name, and refuses an entry that is not a Transport class
    (tmp_path / "pigeon_link.py").write_text(
        "from motion.emulator import Emulator\n"
        "from motion.emulator.simulated import Simulation, SimulatedBus\n"
        "from motion.protocol import WireProtocol\n"
        "class PigeonBus(SimulatedBus):\n"
        "    def __init__(self, ids):\n"
        "        super().__init__(Simulation(Emulator(ids), WireProtocol.CAN))\n"
        "class NotATransport:\n"
        "    pass\n"
    )
    info = tmp_path / "pigeon_link-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: pigeon-link\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(
        "[rmd_motion.transports]\npigeon = pigeon_link:PigeonBus\nbroken = pigeon_link:NotATransport\n"
    )
    code = (
        "import motion.transport as t\n"
        "from motion.errors import TransportError\n"
        "from motion.protocol import Bare, Command\n"
        "with t.open_transport('pigeon', [3]) as bus:\n"
        "    reply, = bus.transact([t.Request(3, Bare(Command.READ_STATUS_1))], bus.clock() + 0.01)\n"
        "    assert reply.ok, reply\n"
        "try:\n"
        "    t.open_transport('broken')\n"
        "except TransportError as e:\n"
        "    assert 'is not a motion.transport.Transport class' in str(e), e\n"
        "else:\n"
        "    raise SystemExit('a class that is no Transport was opened')\n"
        "try:\n"
        "    t.open_transport('owl')\n"
        "except TransportError as e:\n"
        "    assert 'valid: broken, can, pigeon, rs485' in str(e), e\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}
    subprocess.run([sys.executable, "-c", code], check=True, env=env)


def test_backends_are_imported_only_when_used() -> None:
    code = (
        "import sys; import motion.transport as t\n"
        "assert 'can' not in sys.modules and 'serial' not in sys.modules\n"
        "bus = t.open_transport('can', 'virtual', 'lazy'); bus.close()\n"
        "assert 'can' in sys.modules and 'serial' not in sys.modules\n"
        "assert t.Rs485Transport.__name__ == 'Rs485Transport' and 'serial' in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_a_channel_a_session_holds_is_refused_to_a_second_session(channel: str) -> None:
    with rig(channel) as (first, _):  # (the drives' own endpoint on the channel is no session: never refused)
        with pytest.raises(PortHeld, match="held by another rmd-motion session") as refused:
            CanTransport("virtual", channel)
        assert f"CAN interface 'virtual' channel {channel!r}" in str(refused.value) and refused.value.link == "can"
        assert first.transact([status2(1)], first.clock() + 0.2)[0].ok  # the first session goes on
        successor = first.with_family(ProtocolFamily.V3)  # the channel's lock goes with the channel
        first.close()
        with pytest.raises(PortHeld):
            CanTransport("virtual", channel)
        successor.close()
        with CanTransport("virtual", channel) as again:  # released with the channel
            assert not again.closed


def test_an_slcan_adapter_a_session_holds_is_refused_to_another_process(tmp_path: Path) -> None:
    # keyed by the device: a symlink to it, with or without python-can's "@baud" suffix, is the same adapter, and a
    # session in another process is refused before it writes anything to the adapter
    master, slave = os.openpty()
    link = tmp_path / "adapter"
    link.symlink_to(os.ttyname(slave))
    try:
        with CanTransport("slcan", f"{link}@115200", 1_000_000, sleep_after_open=0):
            written = _drain(master)
            other = subprocess.run(
                [
                    sys.executable,
                    "-c",
                    "import sys; from motion.errors import PortHeld; from motion.transport import CanTransport\n"
                    "try:\n"
                    f"    CanTransport('slcan', {os.ttyname(slave)!r}, 1_000_000, sleep_after_open=0)\n"
                    "except PortHeld as exc:\n"
                    "    sys.exit(str(exc))\n",
                ],
                capture_output=True,
                text=True,
                timeout=60,
                check=False,
            )
            assert other.returncode == 1 and "held by another rmd-motion session" in other.stderr, other.stderr
            assert f"process {os.getpid()}" in other.stderr
            assert written and _drain(master) == b""  # the refused session wrote nothing to the adapter
    finally:
        os.close(master)
        os.close(slave)


def _drain(fd: int) -> bytes:
    """What the far end of a pty has received so far."""
    received = b""
    while select.select([fd], [], [], 0.05)[0]:
        received += os.read(fd, 4096)
    return received
