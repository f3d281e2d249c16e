"""`with` for objects that hold a file or a reader and have a `close()`."""

from __future__ import annotations

from types import TracebackType
from typing import TypeVar

_Self = TypeVar("_Self", bound="Closing")  # typing.Self is 3.11; we support 3.10


class Closing:
    """Mixin: `with obj as o:` gives the object itself and calls its `close()` on the way out,
    whatever ends the block."""

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self: _Self) -> _Self:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()
