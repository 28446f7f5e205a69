"""msgpack with numpy arrays, wire-compatible with openpi's `msgpack_numpy`.

An ndarray is packed as the map `{b"__ndarray__": True, b"data": bytes, b"dtype": dtype.str,
b"shape": shape}` and a numpy scalar as `{b"__npgeneric__": True, b"data": value, b"dtype": dtype.str}`
(a `default` hook on packing, an `object_hook` on unpacking). Object, void and complex arrays are
rejected: they cannot be sent without pickling.
"""

from __future__ import annotations

import msgpack
import numpy as np


def _pack_hook(obj):
    if isinstance(obj, np.ndarray | np.generic) and obj.dtype.kind in ("V", "O", "c"):
        raise ValueError(f"cannot send numpy dtype {obj.dtype} over msgpack (object/void/complex)")
    if isinstance(obj, np.ndarray):
        arr = obj if obj.flags.c_contiguous else obj.copy(order="C")  # (ascontiguousarray makes 0-d 1-d)
        return {b"__ndarray__": True, b"data": arr.tobytes(), b"dtype": arr.dtype.str, b"shape": arr.shape}
    if isinstance(obj, np.generic):
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    raise TypeError(f"cannot msgpack an object of type {type(obj).__name__}")


def _unpack_hook(obj: dict):
    if b"__ndarray__" in obj:
        dtype = np.dtype(obj[b"dtype"])
        if dtype.kind in ("V", "O", "c"):
            raise ValueError(f"refusing to unpack numpy dtype {dtype} (object/void/complex)")
        return np.frombuffer(obj[b"data"], dtype=dtype).reshape(tuple(obj[b"shape"])).copy()
    if b"__npgeneric__" in obj:
        return np.dtype(obj[b"dtype"]).type(obj[b"data"])
    return obj


def packb(obj) -> bytes:
    """Serialise plain values, dicts, lists and numpy arrays/scalars."""
    return msgpack.packb(obj, default=_pack_hook, use_bin_type=True)


def unpackb(data: bytes):
    """Inverse of `packb` (arrays come back writable)."""
    return msgpack.unpackb(data, object_hook=_unpack_hook, raw=False)
