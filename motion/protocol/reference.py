"""The command × transport reference tables of ``docs/protocol.md``, generated from the command tables (the older
family's and the V3 family's)."""

from __future__ import annotations

from motion.protocol.rs485_frame import frame_size
from motion.protocol.table import (
    CAN_MULTI_TORQUE_ID,
    COMMANDS,
    MULTI_TORQUE_LAYOUT,
    Direction,
    Field,
    Kind,
    Layout,
    WireProtocol,
)


def _field(f: Field, transport: WireProtocol) -> str:
    # CAN offsets are DATA[i] of the 8-byte payload; RS485 offsets count from the frame's first byte.
    index = f.offset if transport is WireProtocol.CAN else f.offset + 5
    place = f"DATA[{index}]" if f.width == 1 else f"DATA[{index}..{index + f.width - 1}]"
    if f.kind in (Kind.TEXT, Kind.FLOAT32):
        return f"{place} {f.name} {f.ctype}"
    scale = ""
    if f.kind is Kind.REAL and (f.num, f.den) != (1, 1):
        scale = f" ×{f.num}/{f.den}" if f.num != 1 else f" ×1/{f.den}"
    unit = f" {f.unit}" if f.unit else ""
    full = Field(f.name, f.offset, f.width, f.signed)
    limits = f" raw {f.lo}..{f.hi}" if (f.lo, f.hi) != (full.lo, full.hi) else ""
    return f"{place} {f.name} {f.ctype}{scale}{unit}{limits}"


def _layout(layout: Layout | None, transport: WireProtocol) -> str:
    if layout is None:
        return "—"
    body = "; ".join(_field(f, transport) for f in layout.fields) or "no data"
    if transport is WireProtocol.RS485:
        body = f"{frame_size(layout.length)} B: {body}"
    cls = layout.cls.__name__
    return f"`{cls}` {'(echo) ' if layout.echo else ''}{body}"


def markdown_table() -> str:
    """Markdown table of every command: request and reply layout on CAN and on RS485."""
    lines = [
        "| code | command | CAN request | CAN reply | RS485 request | RS485 reply |",
        "|---|---|---|---|---|---|",
    ]
    for code, spec in COMMANDS.items():
        cells = [
            _layout(spec.layout(t, d), t)
            for t in (WireProtocol.CAN, WireProtocol.RS485)
            for d in (Direction.REQUEST, Direction.REPLY)
        ]
        lines.append(f"| 0x{code:02X} | {spec.title} | " + " | ".join(cells) + " |")
    multi = _layout(MULTI_TORQUE_LAYOUT, WireProtocol.CAN)
    lines.append(
        f"| ID 0x{CAN_MULTI_TORQUE_ID:03X} | Multi-motor torque (motors 1–4) | {multi} | "
        "each motor 1–4 replies on 0x140+id like 0xA1, in ascending id order | — | — |"
    )
    return "\n".join(lines) + "\n"


def markdown_table_v3() -> str:
    """Markdown table of every command of the V3 family: request and reply layout (DATA[0..7], the same bytes on CAN
    and in the RS485 frame's data field)."""
    # Imported here: the V3 table imports the older family's modules, this module among their users.
    from motion.protocol.v3.table import COMMANDS_V3, RS485_COMMANDS  # noqa: PLC0415

    lines = ["| code | command | request | reply | RS485 |", "|---|---|---|---|---|"]
    for code, spec in COMMANDS_V3.items():
        request, reply = (_layout(spec.layout(WireProtocol.CAN, d), WireProtocol.CAN) for d in Direction)
        reply = reply if reply != "—" else "no reply"
        lines.append(
            f"| 0x{code:02X} | {spec.title} | {request} | {reply} | {'yes' if code in RS485_COMMANDS else 'no'} |"
        )
    return "\n".join(lines) + "\n"
