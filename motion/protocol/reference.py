"""The command × transport reference table of ``docs/protocol.md``, generated from the command table."""

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
    if f.kind is Kind.TEXT:
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
