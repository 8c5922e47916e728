"""The codec's fast path: one precompiled :class:`struct.Struct` per command, direction and transport.

Everything here is derived at import from the one table (:data:`motion.protocol.table.COMMANDS`); nothing is
declared twice. For each layout that :mod:`struct` can express (field widths 1, 2, 4 and 8 bytes; no text), a
small encoder and decoder are generated as Python source and compiled once, the way :mod:`dataclasses` builds
``__init__``: encoding is a type check and a range check per field and one ``pack``, decoding one ``unpack``, the
checks the table asks for and one message construction.

The fast path never decides an error. When anything is unusual (a value of another type, out of range, not
finite; a reserved byte set; a field outside its range) it returns None and the caller takes the checked path of
:mod:`motion.protocol.table` (``pack_fields`` / ``unpack_fields``), which gives the same result or raises the same
error with the same message as before. So the golden vectors, the round trips and the fuzz invariant (bad bytes
raise only :class:`~motion.errors.DecodeError`) hold for the fast path by construction, and tests compare the two
paths on every command.

Messages are frozen, slotted dataclasses. Their generated ``__init__`` sets each field through
``object.__setattr__`` (it must get past the frozen ``__setattr__``); the decoders build an equal object without it,
through :func:`frozen_builder`: ``object.__new__`` and the classes' own slot descriptors (about twice as fast as
``__init__``). Classes with a ``__post_init__`` or a field without a default that the layout does not carry are built
through ``__init__``.
"""

from __future__ import annotations

import dataclasses
import struct
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, Final, TypeVar

from motion.protocol.messages import Message, MultiMotorTorque
from motion.protocol.table import (
    CAN_PAYLOAD_BYTES,
    COMMANDS,
    MULTI_TORQUE_LAYOUT,
    CommandSpec,
    Direction,
    Field,
    Kind,
    Layout,
    WireProtocol,
)

#: ``encode(message) -> payload``, or None for "take the checked path". May raise TypeError, ValueError,
#: OverflowError, AttributeError or struct.error on odd input; callers treat those as None.
Encoder = Callable[[Message], bytes | None]
#: ``decode(payload) -> message``, or None for "take the checked path". ``payload`` has the layout's size.
Decoder = Callable[[bytes], Message | None]

T = TypeVar("T")


def frozen_builder(cls: type[T]) -> Callable[..., T]:
    """A positional constructor of a frozen, slotted dataclass without ``__post_init__`` that sets the slots
    directly (see the module docstring); the class itself when that does not apply. Every field is required.

    Args:
        cls: the class.
    """
    if hasattr(cls, "__post_init__") or not hasattr(cls, "__slots__") or not dataclasses.is_dataclass(cls):
        return cls
    fields = [f.name for f in dataclasses.fields(cls)]
    env: dict[str, Any] = {}
    names = [f"a{i}" for i in range(len(fields))]
    body = _slot_sets(cls, env)(dict(zip(fields, names, strict=True)))
    source = f"def build({', '.join(names)}):\n    {body}"
    namespace: dict[str, Any] = {}
    exec(compile(source, f"<build {cls.__name__}>", "exec"), env, namespace)
    builder: Callable[..., T] = namespace["build"]
    return builder


#: What the fast encoders may raise on unusual input (every one means: take the checked path).
FALLBACK_ERRORS: Final = (TypeError, ValueError, OverflowError, AttributeError, struct.error)

_STRUCT_CODES: Final = {(1, False): "B", (1, True): "b", (2, False): "H", (2, True): "h"} | {
    (4, False): "I",
    (4, True): "i",
    (8, False): "Q",
    (8, True): "q",
}


@dataclass(frozen=True, slots=True)
class CompiledLayout:
    """The fast encoder and decoder of one layout on one transport in one direction.

    Attributes:
        layout: the table's layout.
        command: the command byte (None for the 0x280 frame).
        size: bytes of the payload (CAN: 8 with the command byte; RS485: the data section).
        packer: the precompiled struct of the whole payload.
        encode: the fast encoder (see :data:`Encoder`).
        decode: the fast decoder (see :data:`Decoder`).
    """

    layout: Layout
    command: IntEnum | None
    size: int
    packer: struct.Struct
    encode: Encoder
    decode: Decoder


def _compilable(layout: Layout) -> bool:
    return all(f.kind not in (Kind.TEXT, Kind.FLOAT32) and (f.width, f.signed) in _STRUCT_CODES for f in layout.fields)


def _full_range(f: Field) -> bool:
    bits = 8 * f.width
    lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if f.signed else (0, (1 << bits) - 1)
    return f.lo == lo and f.hi == hi


def _format(layout: Layout, size: int, command_at_zero: bool) -> tuple[str, list[Field]]:
    """The struct format of a payload: the command byte (CAN), the fields in offset order, pad bytes between."""
    codes = ["<"]
    position = 0
    if command_at_zero:
        codes.append("B")
        position = 1
    ordered = sorted(layout.fields, key=lambda f: f.offset)
    for f in ordered:
        if f.offset < position:
            raise ValueError(f"{layout.cls.__name__}: field {f.name} overlaps the one before it")
        codes.append("x" * (f.offset - position) + _STRUCT_CODES[f.width, f.signed])
        position = f.offset + f.width
    if position > size:
        raise ValueError(f"{layout.cls.__name__}: fields end at byte {position}, beyond {size}")
    codes.append("x" * (size - position))
    return "".join(codes), ordered


def _to_raw_source(f: Field, value: str, raw: str, env: dict[str, Any], lines: list[str]) -> None:
    """Source lines that turn ``value`` into ``raw`` exactly as ``table._to_raw`` does, or return None."""
    if f.kind is Kind.REAL:
        # The checked path computes round(value * den / num) for a float; (x * 1) and (x / 1) are exact, so
        # dropping them gives the same float. Integers take the checked path (it is exact for them).
        # float.__round__ refuses anything but a float (TypeError -> checked path), as a type check would; a
        # division would turn an int or a bool into a float first, so with one the type is checked here.
        expression = value if f.den == 1 else f"{value} * {f.den}"
        if f.num != 1:
            lines.append(f"    if {value}.__class__ is not float: return None")
            expression = f"{expression} / {f.num}"
        lines.append(f"    {raw} = fround({expression})")
    elif f.kind in (Kind.ENUM, Kind.FLAGS):
        enum = env[f"E_{f.name}"] = f.enum
        assert enum is not None
        lines.append(f"    if {value}.__class__ is not E_{f.name}: return None")
        lines.append(f"    {raw} = {value}._value_")
    else:
        lines.append(f"    if {value}.__class__ is not int: return None")
        lines.append(f"    {raw} = {value}")
    if not _full_range(f):
        # Full-range fields are checked by struct.pack itself (struct.error -> checked path).
        lines.append(f"    if not {f.lo} <= {raw} <= {f.hi}: return None")


def _encoder(
    layout: Layout, command: IntEnum | None, ordered: list[Field], packer: struct.Struct, *, lead: bool
) -> Encoder:
    env: dict[str, Any] = {"pack": packer.pack, "fround": float.__round__}
    lines = ["def encode(m):"]
    for name in layout.uncarried:
        lines.append(f"    if m.{name} is not None: return None")
    raws = []
    for i, f in enumerate(ordered):
        lines.append(f"    v{i} = m.{f.name}")
        _to_raw_source(f, f"v{i}", f"r{i}", env, lines)
        raws.append(f"r{i}")
    arguments = ([str(int(command))] if lead and command is not None else []) + raws
    lines.append(f"    return pack({', '.join(arguments)})")
    namespace: dict[str, Any] = {}
    exec(compile("\n".join(lines), f"<encode {layout.cls.__name__}>", "exec"), env, namespace)
    encoder: Encoder = namespace["encode"]
    return encoder


def _uncarried_defaults(cls: type[Message], carried: Collection[str]) -> dict[str, Any] | None:
    """The defaults of ``cls``'s fields a layout does not carry (``carried``: the names it gives values), or None
    where such a field has no default (then a decoder cannot build the message by itself)."""
    defaults: dict[str, Any] = {}
    for fld in dataclasses.fields(cls):
        if fld.name in carried:
            continue
        if fld.default is dataclasses.MISSING:
            return None
        defaults[fld.name] = fld.default
    return defaults


def _constructor(cls: type[Message], names: list[str], env: dict[str, Any]) -> Callable[[list[str]], str] | None:
    """How the decoder builds ``cls`` from source expressions in the order of ``names`` (see the module docstring)."""
    if hasattr(cls, "__post_init__") or not hasattr(cls, "__slots__"):
        return None
    values = _uncarried_defaults(cls, names)
    if values is None:
        return None
    defaults: dict[str, str] = {}
    for i, (name, value) in enumerate(values.items()):
        env[f"D{i}"] = value
        defaults[name] = f"D{i}"
    sets = _slot_sets(cls, env)

    def build(values: list[str]) -> str:
        return sets(dict(zip(names, values, strict=True)) | defaults)

    return build


def _slot_sets(cls: type, env: dict[str, Any]) -> Callable[[Mapping[str, str]], str]:
    """The pure-Python way to build ``cls`` without ``__init__``: ``object.__new__`` and one slot descriptor set per
    field (put into ``env``), as source text from an expression per field name."""
    env["new"] = object.__new__
    env["C"] = cls
    setters = {fld.name: f"S{i}" for i, fld in enumerate(dataclasses.fields(cls))}
    for name, setter in setters.items():
        env[setter] = cls.__dict__[name].__set__

    def source(given: Mapping[str, str]) -> str:
        sets = "; ".join(f"{setters[name]}(o, {expression})" for name, expression in given.items())
        return f"o = new(C); {sets}; return o"

    return source


def _decoder(
    layout: Layout,
    command: IntEnum | None,
    ordered: list[Field],
    packer: struct.Struct,
    *,
    lead: bool,
    check_reserved: bool,
) -> Decoder:
    env: dict[str, Any] = {"unpack": packer.unpack, "from_bytes": int.from_bytes, "CMD": command}
    lines = ["def decode(d):"]
    if check_reserved:
        mask = sum(0xFF << (8 * i) for i in range(int(lead), packer.size) if i not in layout.used)
        if mask:
            lines.append(f"    if from_bytes(d, 'little') & {mask}: return None")
    raws = [f"r{i}" for i in range(len(ordered))]
    skip = "_, " if lead else ""
    target = f"{skip}{', '.join(raws)}," if raws else ""
    if target:
        lines.append(f"    {target} = unpack(d)")
    else:
        lines.append("    unpack(d)")
    values = []
    for i, f in enumerate(ordered):
        raw = f"r{i}"
        if not _full_range(f):
            lines.append(f"    if not {f.lo} <= {raw} <= {f.hi}: return None")
        if f.kind is Kind.REAL:
            # Same expression as Field.physical: raw * num / den.
            values.append(f"{raw} * {f.num} / {f.den}")
        elif f.kind is Kind.ENUM:
            env[f"M_{f.name}"] = f.enum._value2member_map_ if f.enum is not None else {}
            lines.append(f"    e{i} = M_{f.name}.get({raw})")
            lines.append(f"    if e{i} is None: return None")
            values.append(f"e{i}")
        elif f.kind is Kind.FLAGS:
            # The flag's member by value from the enum's own map (an IntFlag adds every combination it has built to
            # it); the enum's call, which is twenty times slower, only for a combination not seen before.
            env[f"E_{f.name}"] = f.enum
            env[f"M_{f.name}"] = f.enum._value2member_map_ if f.enum is not None else {}
            lines.append(f"    e{i} = M_{f.name}.get({raw})")
            lines.append(f"    if e{i} is None: e{i} = E_{f.name}({raw})")
            values.append(f"e{i}")
        else:
            values.append(raw)
    names = [f.name for f in ordered]
    if layout.has_command_field:
        names.append("command")
        values.append("CMD")
    build = _constructor(layout.cls, names, env)
    if build is None:
        env["C"] = layout.cls
        lines.append(f"    return C({', '.join(f'{n}={v}' for n, v in zip(names, values, strict=True))})")
    else:
        lines.append(f"    {build(values)}")
    namespace: dict[str, Any] = {}
    exec(compile("\n".join(lines), f"<decode {layout.cls.__name__}>", "exec"), env, namespace)
    decoder: Decoder = namespace["decode"]
    return decoder


def compile_layout(
    layout: Layout, command: IntEnum | None, transport: WireProtocol, direction: Direction
) -> CompiledLayout | None:
    """The fast path of one layout, or None when struct cannot express it (text, 7-byte fields)."""
    if not _compilable(layout):
        return None
    can = transport is WireProtocol.CAN
    size = CAN_PAYLOAD_BYTES if can else layout.length
    lead = can and command is not None  # the CAN command byte DATA[0] is part of the payload
    format_, ordered = _format(layout, size, command_at_zero=lead)
    packer = struct.Struct(format_)
    return CompiledLayout(
        layout=layout,
        command=command,
        size=size,
        packer=packer,
        encode=_encoder(layout, command, ordered, packer, lead=lead),
        decode=_decoder(layout, command, ordered, packer, lead=lead, check_reserved=direction is Direction.REQUEST),
    )


@dataclass(frozen=True, slots=True)
class Codec:
    """The fast paths of one transport in one direction.

    Attributes:
        encoders: by message class; a class that serves several commands (``command`` is a field) maps to a
            dispatcher on ``message.command``.
        decoders: by command byte (256 entries; None where the checked path must decide).
        layouts: the compiled layouts by command byte (None where none).
    """

    encoders: Mapping[type[Message], Encoder]
    decoders: tuple[Decoder | None, ...]
    layouts: tuple[CompiledLayout | None, ...]


def _dispatcher(by_command: dict[int, Encoder]) -> Encoder:
    get = by_command.get

    def encode(message: Message) -> bytes | None:
        # ``command`` is a field of these classes: an IntEnum member (its _value_ is a plain int, cheap to hash).
        encoder = get(message.command._value_)  # type: ignore[attr-defined]
        return None if encoder is None else encoder(message)

    return encode


def build_codec(transport: WireProtocol, direction: Direction, commands: Mapping[Any, CommandSpec] = COMMANDS) -> Codec:
    """Compile every layout of ``commands`` (a family's table; :data:`COMMANDS` is the older family's) for
    ``transport`` in ``direction``."""
    single: dict[type[Message], CompiledLayout] = {}
    shared: dict[type[Message], dict[int, CompiledLayout]] = {}
    layouts: list[CompiledLayout | None] = [None] * 256
    for spec in commands.values():
        layout = spec.layout(transport, direction)
        if layout is None:
            continue
        compiled = compile_layout(layout, spec.code, transport, direction)
        if compiled is None:
            continue
        layouts[spec.code] = compiled
        if layout.has_command_field:
            shared.setdefault(layout.cls, {})[int(spec.code)] = compiled
        else:
            single[layout.cls] = compiled
    if commands is COMMANDS and transport is WireProtocol.CAN and direction is Direction.REQUEST:
        multi = compile_layout(MULTI_TORQUE_LAYOUT, None, transport, direction)
        if multi is not None:
            single[MultiMotorTorque] = multi
    encoders: dict[type[Message], Encoder] = {cls: c.encode for cls, c in single.items()}
    for cls, by_command in shared.items():
        encoders[cls] = _dispatcher({code: c.encode for code, c in by_command.items()})
    decoders = tuple(c.decode if c is not None else None for c in layouts)
    return Codec(encoders, decoders, tuple(layouts))


#: The fast paths, by transport and direction.
CODECS: Final[Mapping[tuple[WireProtocol, Direction], Codec]] = {
    (t, d): build_codec(t, d) for t in WireProtocol for d in Direction
}
#: The 0x280 frame's decoder (a request without a command byte).
MULTI_TORQUE_DECODE: Final = compile_layout(MULTI_TORQUE_LAYOUT, None, WireProtocol.CAN, Direction.REQUEST)
