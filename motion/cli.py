"""The ``rmd-motion`` command.

Exit codes: 0 done, 1 motion fault (axes halted), 2 usage or configuration error, 3 communication error,
130 interrupted by Ctrl-C.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from motion import __version__
from motion.emulator.cli import add_emulate_arguments, run_emulate
from motion.errors import ConfigError, MotionError, MotionFault, ProtocolError, TransportError
from motion.protocol import (
    Bare,
    Command,
    ErrorFlags,
    Message,
    MotorState,
    MultiMotorTorque,
    MultiTurnPositionSpeed,
    Rs485Parser,
    Status1,
    can_frame,
    rs485_frame,
)

EXIT_OK = 0
EXIT_FAULT = 1
EXIT_USAGE = 2
EXIT_COMMUNICATION = 3
EXIT_INTERRUPTED = 130


def _show(label: str, wire: str, motor_id: int | None, message: Message) -> None:
    target = f"motor {motor_id}" if motor_id is not None else "motors 1-4"
    print(f"  {label:<6} {wire:<58} -> {target}: {message}")


def _demo() -> int:
    """Encode one control cycle's frames on both transports and print them decoded again."""
    requests: list[tuple[int, Message]] = [
        (1, MultiTurnPositionSpeed(angle_deg=90.0, max_speed_dps=360.0)),
        (2, MultiTurnPositionSpeed(angle_deg=-45.5, max_speed_dps=120.0)),
        (3, Bare(Command.READ_STATUS_1)),
    ]
    replies: list[tuple[int, Message]] = [
        (1, MotorState(Command.MULTI_TURN_POSITION_SPEED, 32, 1.6, 355, 4096)),
        (2, MotorState(Command.MULTI_TURN_POSITION_SPEED, 31, -0.8, -118, 12000)),
        (3, Status1(Command.READ_STATUS_1, 36, 24.1, ErrorFlags.NONE)),
    ]
    print("CAN v2.3 (ID: payload)")
    for motor_id, message in requests:
        frame = can_frame.encode_request(message, motor_id)
        decoded = can_frame.decode_request(frame.arbitration_id, frame.data)
        _show("host", f"{frame.arbitration_id:03X}: {frame.data.hex(' ')}", decoded.motor_id, decoded.message)
    for motor_id, message in replies:
        frame = can_frame.encode_reply(message, motor_id)
        rid, reply = can_frame.decode_reply(frame.arbitration_id, frame.data)
        _show("drive", f"{frame.arbitration_id:03X}: {frame.data.hex(' ')}", rid, reply)
    multi = can_frame.encode_request(MultiMotorTorque(1.6, -0.8, 0.0, 0.0))
    decoded = can_frame.decode_request(multi.arbitration_id, multi.data)
    _show("host", f"{multi.arbitration_id:03X}: {multi.data.hex(' ')}", decoded.motor_id, decoded.message)

    print("RS485 v1.62 (frames found in one byte stream with garbage between them)")
    parser = Rs485Parser()
    stream = b"\x00\xff".join(rs485_frame.encode_request(m, i) for i, m in requests)
    parser.feed(stream)
    while (frame485 := parser.next_frame()) is not None:
        raw = frame485.to_bytes()
        motor_id, message = rs485_frame.decode_request(raw)
        _show("host", raw.hex(" "), motor_id, message)
    for motor_id, message in replies:
        raw = rs485_frame.encode_reply(message, motor_id)
        rid, reply = rs485_frame.decode_reply(raw)
        _show("drive", raw.hex(" "), rid, reply)
    print(f"parser: {parser.frames} frames, {parser.dropped_bytes} garbage bytes dropped")
    return EXIT_OK


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``rmd-motion``."""
    parser = argparse.ArgumentParser(prog="rmd-motion", description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--version", action="version", version=f"rmd-motion {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    sub.add_parser("demo", help="encode and decode one control cycle on both transports")
    add_emulate_arguments(
        sub.add_parser("emulate", help="run emulated RMD drives on an slcan or RS485 pseudo-terminal")
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``rmd-motion``; returns the exit code."""
    args = build_parser().parse_args(argv)
    try:
        if args.command == "demo":
            return _demo()
        if args.command == "emulate":
            return run_emulate(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except MotionFault as exc:
        print(f"motion fault, all axes halted: {exc}", file=sys.stderr)
        return EXIT_FAULT
    except (ConfigError, ProtocolError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except TransportError as exc:
        print(f"communication error: {exc}", file=sys.stderr)
        return EXIT_COMMUNICATION
    except MotionError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
