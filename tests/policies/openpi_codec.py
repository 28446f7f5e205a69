"""openpi_client's msgpack-numpy codec, written for the tests from the protocol (not twinbench's own):
numpy arrays travel as {b"__ndarray__": True, b"data", b"dtype", b"shape"}, numpy scalars as
{b"__npgeneric__": True, b"data", b"dtype"}."""

import msgpack
import numpy as np


def pack(obj):
    def default(o):
        if isinstance(o, np.ndarray):
            return {b"__ndarray__": True, b"data": o.tobytes(), b"dtype": o.dtype.str, b"shape": o.shape}
        if isinstance(o, np.generic):
            return {b"__npgeneric__": True, b"data": o.item(), b"dtype": o.dtype.str}
        raise TypeError(type(o))

    return msgpack.packb(obj, default=default)


def unpack(data):
    def hook(d):
        if b"__ndarray__" in d:
            return np.ndarray(buffer=d[b"data"], dtype=np.dtype(d[b"dtype"]), shape=d[b"shape"])
        return d

    return msgpack.unpackb(data, object_hook=hook)
