"""Fixed-point arithmetic and argument checks shared by every bit-exact stage.

Every rounding and saturation rule of the specification (``docs/spec.md``) lives here, once, so
that the stages, the HDL testbenches and the host all mean the same thing by "round" and "clip".

Rules
-----
* Integers are two's complement. A *signed* field of ``w`` bits holds ``-2**(w-1) .. 2**(w-1)-1``,
  an *unsigned* one ``0 .. 2**w - 1``.
* ``round_shift(x, s)`` divides by ``2**s`` rounding half up (toward +infinity):
  ``(x + 2**(s-1)) >> s`` with an arithmetic (flooring) shift; ``s == 0`` returns ``x``.
  This is what one adder and a wire shift give in hardware.
* ``saturate(x, w, signed)`` clips to the range of a ``w``-bit field; nothing ever wraps silently.
"""

from __future__ import annotations

import numbers

import numpy as np

__all__ = [
    "check_array",
    "check_int",
    "int_range",
    "round_shift",
    "saturate",
]


def int_range(width: int, signed: bool) -> tuple[int, int]:
    """Return ``(lo, hi)``, the inclusive range of a ``width``-bit field."""
    if signed:
        return -(1 << (width - 1)), (1 << (width - 1)) - 1
    return 0, (1 << width) - 1


def saturate(x, width: int, signed: bool = True):
    """Clip ``x`` (int array or int) to the range of a ``width``-bit field.

    Returns an ``int64`` array (or a Python int for a scalar input).
    """
    lo, hi = int_range(width, signed)
    if isinstance(x, numbers.Integral):
        return min(max(int(x), lo), hi)
    return np.clip(np.asarray(x, dtype=np.int64), lo, hi)


def round_shift(x, shift: int):
    """Divide by ``2**shift``, rounding half up (arithmetic shift after adding half an LSB).

    Parameters
    ----------
    x : int or array of int
        Value(s) to scale; arrays are computed in ``int64``.
    shift : int
        Non-negative number of bits to drop.
    """
    if shift < 0:
        raise ValueError(f"shift must be >= 0, not {shift!r}")
    if isinstance(x, numbers.Integral):
        return (int(x) + (1 << (shift - 1))) >> shift if shift else int(x)
    x = np.asarray(x, dtype=np.int64)
    if shift == 0:
        return x
    return (x + (1 << (shift - 1))) >> shift


def check_int(name: str, value, lo: int, hi: int) -> int:
    """Return ``value`` as an int if it is an integer in ``lo..hi``, else raise ``ValueError``.

    The message names the parameter and the value given, as every bad-input error here does.
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name} must be an integer in {lo}..{hi}, not {value!r}")
    if not lo <= value <= hi:
        raise ValueError(f"{name} must be in {lo}..{hi}, not {value!r}")
    return int(value)


def check_array(name: str, x, dtype=None, ndim_min: int = 1, last_dims: tuple = ()) -> np.ndarray:
    """Check an input array's dtype and trailing shape; return it as an ndarray (no copy).

    Parameters
    ----------
    name : str
        Parameter name for the error message.
    x : array_like
        The array to check.
    dtype : numpy dtype or tuple of dtypes, optional
        Accepted dtype(s); integer stages refuse to guess a cast (a float or a wider int
        could wrap).
    ndim_min : int
        Minimum number of dimensions.
    last_dims : tuple of int or None
        Required sizes of the trailing dimensions (``None`` for any size).
    """
    arr = np.asarray(x)
    if dtype is not None:
        allowed = dtype if isinstance(dtype, tuple) else (dtype,)
        if arr.dtype not in [np.dtype(d) for d in allowed]:
            names = " or ".join(np.dtype(d).name for d in allowed)
            raise ValueError(f"{name} must have dtype {names}, not {arr.dtype.name}")
    if arr.ndim < max(ndim_min, len(last_dims)):
        raise ValueError(
            f"{name} must have at least {max(ndim_min, len(last_dims))} dimensions, "
            f"not shape {arr.shape}"
        )
    for i, want in enumerate(last_dims):
        got = arr.shape[arr.ndim - len(last_dims) + i]
        if want is not None and got != want:
            pos = -len(last_dims) + i
            raise ValueError(f"{name} must have size {want} on axis {pos}, not shape {arr.shape}")
    return arr
