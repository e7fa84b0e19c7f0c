"""Input validation at dqm's edges: clear errors that name the problem."""
from __future__ import annotations

from typing import Tuple

import numpy as np


class InputError(ValueError):
    """Raised for input that dqm cannot use; the message names the input and the problem."""


def has_repeats(values) -> bool:
    """Whether some value occurs twice in ``values``: a sort and a comparison of neighbours (``np.unique``
    imports ``numpy.ma`` on its first call, about 20 ms of CPU at a job's start in every process that checks)."""
    s = np.sort(np.asarray(values).ravel())
    return bool(len(s) > 1 and (s[1:] == s[:-1]).any())


def check_descriptors(descriptors, name: str = "descriptors", keep_integer: bool = False) -> np.ndarray:
    """Return descriptors as a C-contiguous float64 (n, dim) array, or raise InputError.

    Accepts any real floating or unsigned/signed integer dtype (uint8 SIFT
    included). Rejects other dtypes, non-2-D shapes, zero dimension, NaN and inf.
    ``keep_integer``: integer arrays come back in their own dtype (uint8 stays
    uint8: no float64 copy, 8x less memory; integers are always finite).
    """
    arr = np.asarray(descriptors)
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise InputError(f"{name} must be a float or integer array, got dtype {arr.dtype}")
    if arr.dtype == np.bool_:
        raise InputError(f"{name} must be a float or integer array, got dtype bool")
    if arr.ndim != 2:
        raise InputError(f"{name} must be 2-D (features x dimensions), got shape {arr.shape}")
    if arr.shape[1] == 0:
        raise InputError(f"{name} has zero dimensions per feature (shape {arr.shape})")
    if keep_integer and arr.dtype.kind in "iu":
        return np.ascontiguousarray(arr)
    out = np.ascontiguousarray(arr, dtype=np.float64)
    if out.size and not np.isfinite(out).all():
        bad = np.flatnonzero(~np.isfinite(out).all(axis=1))
        kind = "NaN" if np.isnan(out[bad[0]]).any() else "inf"
        raise InputError(
            f"{name} contain {kind} (or other non-finite values) in {len(bad)} row(s), first at row {bad[0]}"
        )
    return out


#: descriptor magnitudes within 2^-MAGNITUDE_EXP .. 2^MAGNITUDE_EXP are used as they are: squared
#: distances of such vectors neither overflow nor underflow float32, in which the all-pairs GEMM runs
MAGNITUDE_EXP = 40


def magnitude_exponent(X: np.ndarray) -> int:
    """The power of two that brings the largest |value| of ``X`` into [1, 2), or 0 when ``X`` is already
    within the safe range (2^-40 .. 2^40; all zeros count as safe).

    QuickMatch does not depend on a common scale factor of all descriptors, and multiplying by a
    power of two is exact in floating point, so ``np.ldexp(X, -e)`` gives the same clusters with
    safe magnitudes (sigma and distances scale back exactly by ``2^e``).
    """
    if X.size == 0 or X.dtype in (np.uint8, np.int8, np.uint16, np.int16, np.uint32, np.int32):
        return 0  # small integer types are always within the range
    top = float(max(abs(float(X.max())), abs(float(X.min()))))
    if top == 0.0 or 2.0 ** -MAGNITUDE_EXP <= top <= 2.0 ** MAGNITUDE_EXP:
        return 0
    return int(np.frexp(top)[1]) - 1


def check_magnitude(X: np.ndarray, name: str = "descriptors") -> None:
    """Refuse descriptors outside the safe magnitude range (where a caller cannot rescale them all at once:
    online updates, agents that each hold part of the data), naming the largest value."""
    e = magnitude_exponent(X)
    if e:
        top = float(max(abs(float(X.max())), abs(float(X.min()))))
        raise InputError(
            f"{name}: the largest magnitude {top:.3g} is outside the range {2.0 ** -MAGNITUDE_EXP:.2g} .. "
            f"{2.0 ** MAGNITUDE_EXP:.2g} where squared distances are safe in float32; multiply every "
            f"descriptor by the same factor, e.g. 2^{-e} (the clusters do not depend on a common scale)")


def check_image_ids(image_ids, n: int, name: str = "image_ids") -> np.ndarray:
    """Return image ids as an int64 (n,) array, or raise InputError."""
    arr = np.asarray(image_ids)
    if arr.ndim != 1:
        raise InputError(f"{name} must be 1-D (one image id per feature), got shape {arr.shape}")
    if len(arr) != n:
        raise InputError(f"{name} has {len(arr)} entries but there are {n} descriptors (one id per row needed)")
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    if not np.issubdtype(arr.dtype, np.integer):
        if np.issubdtype(arr.dtype, np.floating) and np.isfinite(arr).all() and (arr == np.round(arr)).all():
            arr = arr.astype(np.int64)
        else:
            raise InputError(f"{name} must be integers, got dtype {arr.dtype}")
    return arr.astype(np.int64, copy=False)


def check_positive(value, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a positive number, got {value!r}") from None
    if not np.isfinite(v) or v <= 0:
        raise InputError(f"{name} must be a positive finite number, got {value!r}")
    return v


def check_positive_int(value, name: str) -> int:
    """Return ``value`` as an int >= 1, or raise InputError naming it."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise InputError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def positive_int_arg(text: str) -> int:
    """argparse ``type=`` for options that must be whole numbers >= 1 (``--threads``, ``--agents``)."""
    import argparse

    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {v}")
    return v


def check_choice(value, name: str, choices: Tuple[str, ...]) -> str:
    if value not in choices:
        raise InputError(f"{name} must be one of {', '.join(repr(c) for c in choices)}; got {value!r}")
    return value
