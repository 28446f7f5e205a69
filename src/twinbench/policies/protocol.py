"""The policy-server wire protocol (openpi's), shared by the client (`policies.remote`) and the server
(`policies.server`): constants, the API-key header and the msgpack-numpy codec.

A connection is one websocket (`ws://HOST:PORT`, compression off). The server first sends a metadata map
(`USES_ENVIRONMENT_STATE_KEY`: whether the served policy acts from the task's privileged state); then
each binary frame from the client is a packed observation map, answered by a map holding the action
chunk under `ACTIONS_KEY` ((T, A) or (A,)) and `TIMING_KEY` (`{"infer_ms": float}`). A text frame from
the server is its error report, after which it closes the connection. Frames over the receiver's
`max_message_bytes` (default `DEFAULT_MAX_MESSAGE_BYTES`) close the connection with code 1009. With an
API key (`API_KEY_ENV`), every client sends `AUTH_HEADER: api_key_value(key)` (else HTTP 401).

Codec (`packb`, `unpackb`): msgpack with numpy arrays, wire-compatible with openpi's `msgpack_numpy`.
An ndarray is packed as the map `{b"__ndarray__": True, b"data": bytes, b"dtype": dtype.str,
b"shape": shape}` and a numpy scalar as `{b"__npgeneric__": True, b"data": value, b"dtype": dtype.str}`
(a `default` hook on packing, an `object_hook` on unpacking). Only plain bool / integer / float /
string dtypes travel: object, void, complex and structured dtypes are rejected (they cannot be sent
without pickling). Unpacking is bounded: at most `max_containers` maps + lists per message (a 5 MB
message of 5 million empty arrays would otherwise cost hundreds of MB), and a malformed message raises
`MessageError` (a ValueError), never something else.
"""

from __future__ import annotations

import msgpack
import numpy as np

from twinbench.errors import InputError

API_KEY_ENV = "TWINBENCH_API_KEY"  # the key, on both sides (unset or empty: none)
AUTH_HEADER = "Authorization"
DEFAULT_MAX_MESSAGE_BYTES = 64 * 2**20  # an observation: a few camera images (848x480x3 is 1.2 MB)
ACTIONS_KEY = "actions"  # reply: the action chunk
TIMING_KEY = "server_timing"  # reply: {"infer_ms": ...}
USES_ENVIRONMENT_STATE_KEY = "uses_environment_state"  # metadata: send the privileged environment_state
MAX_CONTAINERS = 100_000  # maps + lists (an ndarray is one map) in one unpacked message
_KINDS = "biufUS"  # bool, signed, unsigned, float, unicode, bytes


class MessageError(InputError):
    """A message that is not valid msgpack-numpy, or exceeds a limit."""


def api_key_value(api_key: str) -> str:
    """The `Authorization` header value that carries `api_key` (openpi's form)."""
    return f"Api-Key {api_key}"


def _check_dtype(dtype: np.dtype, action: str) -> np.dtype:
    if dtype.kind not in _KINDS or dtype.fields is not None or dtype.subdtype is not None:
        raise MessageError(f"refusing to {action} numpy dtype {dtype} (only bool/int/float/str arrays)")
    return dtype


def _pack_hook(obj):
    if isinstance(obj, np.ndarray | np.generic) and obj.dtype.kind in ("V", "O", "c"):
        raise ValueError(f"cannot send numpy dtype {obj.dtype} over msgpack (object/void/complex)")
    if isinstance(obj, np.ndarray):
        arr = obj if obj.flags.c_contiguous else obj.copy(order="C")  # (ascontiguousarray makes 0-d 1-d)
        return {b"__ndarray__": True, b"data": arr.tobytes(), b"dtype": arr.dtype.str, b"shape": arr.shape}
    if isinstance(obj, np.generic):
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    raise TypeError(f"cannot msgpack an object of type {type(obj).__name__}")


def _decode_ndarray(obj: dict):
    try:
        dtype = _check_dtype(np.dtype(obj[b"dtype"]), "unpack")
        shape = tuple(int(v) for v in obj[b"shape"])
        data = obj[b"data"]
        if not isinstance(data, bytes) or any(v < 0 for v in shape):
            raise MessageError("bad ndarray entry")
        return np.frombuffer(data, dtype=dtype).reshape(shape).copy()
    except MessageError:
        raise
    except (KeyError, TypeError, ValueError) as err:
        raise MessageError(f"malformed ndarray entry: {type(err).__name__}: {err}") from None


def _decode_generic(obj: dict):
    try:
        return _check_dtype(np.dtype(obj[b"dtype"]), "unpack").type(obj[b"data"])
    except MessageError:
        raise
    except (KeyError, TypeError, ValueError, OverflowError) as err:
        raise MessageError(f"malformed numpy scalar entry: {type(err).__name__}: {err}") from None


def packb(obj) -> bytes:
    """Serialise plain values, dicts, lists and numpy arrays/scalars."""
    return msgpack.packb(obj, default=_pack_hook, use_bin_type=True)


def unpackb(data: bytes, *, max_containers: int = MAX_CONTAINERS):
    """Inverse of `packb` (arrays come back writable); MessageError on malformed or oversized input."""
    count = [0]

    def budget() -> None:
        count[0] += 1
        if count[0] > max_containers:
            raise MessageError(f"message holds more than {max_containers} maps/lists (limit)")

    def object_hook(obj: dict):
        budget()
        if b"__ndarray__" in obj:
            return _decode_ndarray(obj)
        if b"__npgeneric__" in obj:
            return _decode_generic(obj)
        return obj

    def list_hook(obj: list):
        budget()
        return obj

    if not isinstance(data, bytes | bytearray | memoryview):
        raise MessageError(f"expected a binary message, got {type(data).__name__}")
    try:
        return msgpack.unpackb(data, object_hook=object_hook, list_hook=list_hook, raw=False,
                               max_array_len=max_containers, max_map_len=max_containers)
    except MessageError:
        raise
    except (ValueError, TypeError, msgpack.UnpackException, RecursionError) as err:
        raise MessageError(f"not a valid msgpack message: {type(err).__name__}: {err}") from None
