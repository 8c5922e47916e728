"""Types of the optional C extension built from _speedups.c (see there)."""

from typing import Any

import numpy as np
from numpy.typing import NDArray

class SlotBuilder:
    cls: type
    names: tuple[str, ...]
    def __init__(self, cls: type, names: tuple[str, ...]) -> None: ...
    def __call__(self, *values: Any) -> Any: ...

def chase(
    x: NDArray[np.float64],
    v: NDArray[np.float64],
    dt: float,
    target: NDArray[np.float64],
    cap: NDArray[np.float64],
    gain: NDArray[np.float64],
    accel: NDArray[np.float64],
    max_step: float,
    /,
) -> None: ...

_F64 = NDArray[np.float64]

def torque_pd(tau: _F64, kp: _F64, target: _F64, x: _F64, kd: _F64, ref_v: _F64, v: _F64, /) -> None: ...
def moved_beyond(a: _F64, b: _F64, limit: float, /) -> bool: ...
def torque_advance(
    x: _F64,
    v: _F64,
    x_law: _F64,
    v_law: _F64,
    expected_deg: _F64,
    expected_dps: _F64,
    lag: _F64,
    a: _F64,
    target: _F64,
    dt: float,
    /,
) -> None: ...
def torque_law(
    accel: _F64,
    tau: _F64,
    target: _F64,
    ref_v: _F64,
    ref_a: _F64,
    reference_deg: _F64,
    reference_dps: _F64,
    reference_dps2: _F64,
    kp: _F64,
    x_law: _F64,
    kd: _F64,
    v_law: _F64,
    lo: _F64,
    hi: _F64,
    mass_inv: _F64,
    mass: _F64 | None,
    rad_per_deg: float,
    deg_per_rad: float,
    /,
) -> None: ...
def torque_currents(
    amps: _F64,
    torque: _F64,
    nm_per_a: _F64,
    raw_limit: _F64,
    limited: NDArray[np.bool_],
    addend: _F64 | None,
    raw_per_a: float,
    amps_num: float,
    amps_den: float,
    /,
) -> int | None: ...
def gather_scaled(out: _F64, src: Any, order: NDArray[np.intp], factor: float, /) -> None: ...
def stack_rows(out: _F64, rows: tuple[NDArray[Any], ...], /) -> None: ...

class StateAbsorber:
    def __init__(self, index: dict[int, int], state_type: type, *arrays: NDArray[Any]) -> None: ...
    def __call__(self, replies: list[Any] | tuple[Any, ...], start: int, keep_fresh: bool, /) -> int: ...

class CLayout:
    def __init__(
        self,
        command: int,
        size: int,
        fields: tuple[tuple[Any, ...], ...],
        uncarried: tuple[str, ...],
        builder: Any,
        sources: tuple[int, ...],
        constants: tuple[Any, ...],
    ) -> None: ...
    def encode(self, message: Any, /) -> bytes | None: ...
    def decode(self, payload: bytes, /) -> Any: ...

class CanRequestEncoder:
    fallback: Any
    def __init__(
        self,
        layouts: dict[type, CLayout],
        shared: dict[type, dict[int, CLayout]],
        frame: Any,
        special: type,
        special_id: int,
        id_base: int,
        id_min: int,
        id_max: int,
        fallback: Any,
    ) -> None: ...
    def __call__(self, message: Any, motor_id: int = 1) -> Any: ...

class CanReplyDecoder:
    fallback: Any
    def __init__(
        self, layouts: tuple[CLayout | None, ...], id_base: int, id_min: int, id_max: int, fallback: Any
    ) -> None: ...
    def __call__(self, arbitration_id: int, data: bytes) -> tuple[int, Any]: ...

ABI: int
