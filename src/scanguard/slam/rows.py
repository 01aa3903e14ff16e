"""`Rows`: values appended one at a time into one numpy buffer that doubles.

A back end keeps a few numbers per scan for the whole recording (an odometry pose, an index, a
flag). As Python lists of small arrays and boxed numbers they cost 100-200 bytes a scan each;
here they cost their ``itemsize`` (amortised; at most twice that while the buffer has room).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, DTypeLike, NDArray


class Rows:
    """Rows of one shape and dtype, appended one at a time (amortised O(1)).

    Args:
        dtype: Element type.
        shape: Shape of one row (``()``: a scalar per row).
        capacity: Initial number of rows the buffer holds.
    """

    def __init__(self, dtype: DTypeLike, shape: tuple[int, ...] = (), capacity: int = 64) -> None:
        self._buf: NDArray[Any] = np.empty((max(1, capacity), *shape), dtype=dtype)
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def append(self, row: ArrayLike) -> None:
        """Append one row (copied into the buffer)."""
        if self._n == len(self._buf):
            self._buf = np.concatenate([self._buf, np.empty_like(self._buf)])
        self._buf[self._n] = row
        self._n += 1

    def __getitem__(self, i: int) -> Any:
        if not -self._n <= i < self._n:
            raise IndexError(f"row {i} of {self._n}")
        return self._buf[i % self._n]

    @property
    def values(self) -> NDArray[Any]:
        """The rows so far, ``(n, *shape)`` (a view: valid until the next `append`)."""
        return self._buf[: self._n]


__all__ = ["Rows"]
