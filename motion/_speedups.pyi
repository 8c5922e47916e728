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
