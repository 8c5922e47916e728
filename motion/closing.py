"""One context-manager protocol for everything that holds a resource until it is closed."""

from __future__ import annotations

import types
from typing import Self


class Closing:
    """``with thing:`` closes it at the end (:meth:`close`, defined by the class); ``__enter__`` returns it."""

    def close(self) -> object:
        """Release what the object holds (once; a second call does nothing); what it returns is the class's."""
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: types.TracebackType | None
    ) -> None:
        self.close()
