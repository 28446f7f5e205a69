"""Read and write trained PhysTwin cases without executing anything from the files (DESIGN §11).

A PhysTwin case is three files (PhysTwin repository layout in brackets):

- `final_data.pkl` [data/different_types/CASE/]: a dict of numpy arrays: `object_points` (F, N, 3),
  `object_colors` (F, N, 3), `object_visibilities` (F, N), `object_motions_valid` (F, N),
  `controller_points` (F, K, 3), `surface_points` (S, 3), `interior_points` (I, 3);
- `optimal_params.pkl` [experiments_optimization/CASE/]: stage-1 (CMA-ES) scalars: `global_spring_Y`,
  `object_radius`, `object_max_neighbours`, `controller_radius`, `controller_max_neighbours`,
  `collide_elas`, `collide_fric`, `collide_object_elas`, `collide_object_fric`, `collision_dist`,
  `drag_damping`, `dashpot_damping`;
- `best_EPOCH.pth` [experiments/CASE/train/]: a torch zip archive of a dict with `spring_Y` (M,) (Y, not
  log Y; object springs first, then controller springs), `collide_elas`, `collide_fric`,
  `collide_object_elas`, `collide_object_fric` (1-element tensors), `num_object_springs`, `epoch`.

`load_pickle` / `load_torch_zip` use a restricted unpickler: it admits numpy arrays and scalars (their
reconstruct / dtype / frombuffer globals), torch tensors' raw storage bytes (rebuilt as numpy arrays
from the archive, so torch is not needed) and plain values (dict, list, tuple, str, bytes, int, float,
bool, None). Any other global raises `PhysTwinFormatError` before anything is called.

PhysTwin's physics frame: the real-data configs use `reverse_z: true` (gravity and the ground normal
point along +z, objects at z < 0); importing turns such a case by half a turn about x (x, -y, -z),
a proper rotation, into twinbench's z-up frame. Springs are rebuilt by PhysTwin's rule in its order:
Open3D's hybrid search returns the query point itself among the `object_max_neighbours`, which PhysTwin
drops, so each particle links to at most `object_max_neighbours - 1` others
(`physics.radius_springs(points, object_radius, object_max_neighbours - 1)`); controller points link to
at most `controller_max_neighbours` particles within `controller_radius`.

PhysTwin's config loader (`qqtt/utils/config.py`, `Config.update_from_dict`) casts every loaded value to
the type of that field's default. Of the stage-1 scalars, `drag_damping` (default 3), `dashpot_damping`
(default 100) and the two `*_max_neighbours` have integer defaults, so PhysTwin runs a trained drag of 2.6
as 2 and a dashpot of 75.5 as 75 (Python `int`, truncation toward zero); the others are floats. Importing
applies the same rule (`phystwin_config`); the files keep the values as written.
"""

from __future__ import annotations

import io
import json
import math
import pickle
import re
import zipfile
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twinbench.errors import InputError

FINAL_KEYS = (
    "object_points",
    "object_colors",
    "object_visibilities",
    "object_motions_valid",
    "controller_points",
    "surface_points",
    "interior_points",
)
OPTIMAL_KEYS = (
    "global_spring_Y",
    "object_radius",
    "object_max_neighbours",
    "controller_radius",
    "controller_max_neighbours",
    "collide_elas",
    "collide_fric",
    "collide_object_elas",
    "collide_object_fric",
    "collision_dist",
    "drag_damping",
    "dashpot_damping",
)
CHECKPOINT_KEYS = ("spring_Y", "collide_elas", "collide_fric", "collide_object_elas", "collide_object_fric",
                   "num_object_springs")
# stage-1 fields whose PhysTwin default is an int: its loader truncates the trained value with int()
PHYSTWIN_INT_FIELDS = ("object_max_neighbours", "controller_max_neighbours", "drag_damping",
                       "dashpot_damping")
FLIP_Z = np.diag([1.0, -1.0, -1.0, 1.0])  # half a turn about x: PhysTwin reverse_z frame <-> z up


# What the restricted reader builds at most (a trained case holds a few arrays of some MB): bytes of array
# data per file, values in the loaded tree (a value shared by several parents counted at each), nesting.
MAX_BYTES = 1 << 29
MAX_VALUES = 1_000_000
MAX_DEPTH = 64
MAX_TORCH_PICKLE = 16 << 20  # a torch archive's data.pkl (its tensors' data are separate records)


class PhysTwinFormatError(InputError):
    """A PhysTwin file that cannot be read safely or lacks a field (message names file, field and fix)."""


# ------------------------------------------------------------------------------------------------
# restricted unpickling


@dataclass(frozen=True)
class _StorageType:
    name: str
    dtype: np.dtype | None  # None: bfloat16 (converted to float32)


_TORCH_STORAGES = {
    "FloatStorage": np.dtype("<f4"),
    "DoubleStorage": np.dtype("<f8"),
    "HalfStorage": np.dtype("<f2"),
    "BFloat16Storage": None,
    "LongStorage": np.dtype("<i8"),
    "IntStorage": np.dtype("<i4"),
    "ShortStorage": np.dtype("<i2"),
    "CharStorage": np.dtype("i1"),
    "ByteStorage": np.dtype("u1"),
    "BoolStorage": np.dtype("?"),
}


@dataclass
class _Storage:
    data: np.ndarray  # 1-D, the storage's elements


def _numpy_globals() -> dict[tuple[str, str], object]:
    try:
        from numpy._core import multiarray, numeric  # numpy >= 2
    except ImportError:  # numpy 1.x (whose numpy._core is a stub without numeric)
        from numpy.core import multiarray, numeric

    out: dict[tuple[str, str], object] = {}
    for mod in ("numpy.core", "numpy._core"):
        out[(f"{mod}.multiarray", "_reconstruct")] = multiarray._reconstruct
        out[(f"{mod}.multiarray", "scalar")] = multiarray.scalar
        out[(f"{mod}.numeric", "_frombuffer")] = numeric._frombuffer
    out[("numpy", "ndarray")] = np.ndarray
    out[("numpy", "dtype")] = np.dtype
    out[("_codecs", "encode")] = _latin1_bytes  # protocol <= 2 writes bytes as _codecs.encode(str, "latin1")
    out[("__builtin__", "bytes")] = out[("builtins", "bytes")] = _empty_bytes  # ... and b"" as bytes()
    return out


def _empty_bytes(*args):
    if args:
        raise PhysTwinFormatError("unexpected bytes(...) call with arguments in a pickle")
    return b""


def _latin1_bytes(text, encoding="latin1"):
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
        raise PhysTwinFormatError(f"unexpected _codecs.encode({type(text).__name__}, {encoding!r})")
    return text.encode("latin1")


def _rebuild_tensor(storage, storage_offset, size, stride, requires_grad=False, backward_hooks=None,
                    metadata=None):
    """torch._utils._rebuild_tensor_v2, as a numpy copy; the view is bounds-checked first."""
    if not isinstance(storage, _Storage):
        raise PhysTwinFormatError("tensor without a storage record")
    size = tuple(int(s) for s in size)
    stride = tuple(int(s) for s in stride)
    off = int(storage_offset)
    if len(size) != len(stride) or off < 0 or any(s < 0 for s in size) or any(s < 0 for s in stride):
        raise PhysTwinFormatError(f"tensor with invalid size {size} / stride {stride} / offset {off}")
    n = storage.data.shape[0]
    count = math.prod(size)
    if count * storage.data.itemsize > MAX_BYTES:
        raise PhysTwinFormatError(f"tensor of size {size} exceeds {MAX_BYTES >> 20} MiB")
    if count == 0:
        return np.zeros(size, dtype=storage.data.dtype)
    last = off + sum((sz - 1) * st for sz, st in zip(size, stride, strict=True))
    if last >= n:
        raise PhysTwinFormatError(f"tensor view reaches element {last} of a storage of {n}")
    item = storage.data.itemsize
    view = np.lib.stride_tricks.as_strided(
        storage.data[off:], shape=size, strides=tuple(s * item for s in stride), writeable=False
    )
    return np.array(view)


def _rebuild_parameter(data, requires_grad=False, backward_hooks=None):
    return data


_TORCH_GLOBALS = {
    ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor,
    ("torch._utils", "_rebuild_parameter"): _rebuild_parameter,
    ("collections", "OrderedDict"): OrderedDict,
}


class _Records:
    """A torch archive's storage records, each read (decompressed) only as far as its tensor needs, all of
    them together at most MAX_BYTES: a record that inflates without bound is never read whole."""

    def __init__(self, zf: zipfile.ZipFile, prefix: str, source: str):
        self._zf, self._source = zf, source
        self._infos = {i.filename[len(prefix) + 5:]: i for i in zf.infolist()
                       if i.filename.startswith(prefix + "data/")}
        self._read: dict[str, bytes] = {}
        self._left = MAX_BYTES

    def get(self, key: str, nbytes: int) -> bytes | None:
        info = self._infos.get(key)
        if info is None:
            return None
        have = self._read.get(key, b"")
        if len(have) < nbytes:
            if nbytes - len(have) > self._left:
                raise PhysTwinFormatError(f"{self._source}: data/{key}: the tensors need more than "
                                          f"{MAX_BYTES >> 20} MiB; not a PhysTwin checkpoint")
            with self._zf.open(info) as f:
                have = f.read(nbytes)
            self._left -= len(have) - len(self._read.get(key, b""))
            self._read[key] = have
        return have[:nbytes]


class _RestrictedUnpickler(pickle.Unpickler):
    def __init__(self, file, *, source: str, records: _Records | None = None, byteorder: str = "little"):
        super().__init__(file)
        self._source = source
        self._records = records
        self._byteorder = byteorder
        self._allowed = _numpy_globals()
        if records is not None:
            self._allowed.update(_TORCH_GLOBALS)

    def find_class(self, module, name):
        obj = self._allowed.get((module, name))
        if obj is not None:
            return obj
        if self._records is not None and module == "torch" and name in _TORCH_STORAGES:
            return _StorageType(name, _TORCH_STORAGES[name])
        raise PhysTwinFormatError(
            f"{self._source}: refuses to load the pickled object {module}.{name}: only numpy arrays, "
            "tensor data and plain values are read (nothing from the file is executed); re-save the "
            "file with plain arrays"
        )

    def persistent_load(self, pid):
        if self._records is None or not isinstance(pid, tuple) or len(pid) != 5 or pid[0] != "storage":
            raise PhysTwinFormatError(f"{self._source}: unexpected persistent reference {pid!r:.80}")
        _, stype, key, _location, numel = pid
        if not isinstance(stype, _StorageType):
            raise PhysTwinFormatError(f"{self._source}: storage of unknown type {stype!r:.80}")
        if isinstance(numel, bool) or not isinstance(numel, int) or numel < 0:
            raise PhysTwinFormatError(f"{self._source}: data/{key}: element count {type(numel).__name__} "
                                      "is not a count")
        nbytes = numel * (2 if stype.dtype is None else stype.dtype.itemsize)
        raw = self._records.get(str(key), nbytes)
        if raw is None:
            raise PhysTwinFormatError(f"{self._source}: the archive has no data/{key} record")
        if stype.dtype is None:  # bfloat16 -> float32 (upper 16 bits)
            u16 = np.frombuffer(raw, dtype="<u2" if self._byteorder == "little" else ">u2")
            data = (u16.astype(np.uint32) << 16).view(np.float32)
        else:
            dt = stype.dtype if self._byteorder == "little" else stype.dtype.newbyteorder(">")
            if len(raw) % dt.itemsize:
                raise PhysTwinFormatError(f"{self._source}: data/{key} is not a whole number of {dt}")
            data = np.frombuffer(raw, dtype=dt).astype(dt.newbyteorder("="))
        if int(numel) > len(data):
            raise PhysTwinFormatError(f"{self._source}: data/{key} holds {len(data)} elements, needs {numel}")
        return _Storage(data)


def _label(key) -> str:
    return repr(key)[:40] if isinstance(key, (str, int, float, bytes)) else type(key).__name__


def _check_plain(obj, source: str) -> None:
    """Reject anything but plain values and non-object numpy arrays/scalars in the loaded tree, a tree
    deeper than MAX_DEPTH, one that contains itself, and one of more than MAX_VALUES values or MAX_BYTES
    of arrays counting a shared value at each of its parents (a small file of shared references can
    stand for 2^60 values). Iterative and linear in the distinct values."""
    sizes: dict[int, tuple[int, int]] = {}  # id -> (values, array bytes) of the value's expanded tree
    open_: set[int] = set()
    stack = [(obj, "", 0, False)]
    while stack:
        value, where, depth, done = stack.pop()
        key = id(value)
        if value is None or isinstance(value, (bool, int, float, str, bytes)):
            sizes[key] = (1, 0)
            continue
        if isinstance(value, np.ndarray | np.generic):
            if value.dtype.hasobject:
                raise PhysTwinFormatError(f"{source}: {where or 'value'} is an object array; "
                                          "only plain arrays")
            sizes[key] = (1, value.nbytes)
            continue
        if not isinstance(value, (dict, list, tuple)):
            raise PhysTwinFormatError(f"{source}: {where or 'value'} has type {type(value).__name__}, "
                                      "not a plain value")
        items = [(v, f"{where}[{_label(k)}]") for k, v in value.items()] + [(k, where) for k in value] \
            if isinstance(value, dict) else [(v, f"{where}[{i}]") for i, v in enumerate(value)]
        if done:
            open_.discard(key)
            n = 1 + sum(sizes[id(v)][0] for v, _ in items)
            b = sum(sizes[id(v)][1] for v, _ in items)
            if n > MAX_VALUES or b > MAX_BYTES:
                raise PhysTwinFormatError(
                    f"{source}: {where or 'the file'} expands to more than {MAX_VALUES} values or "
                    f"{MAX_BYTES >> 20} MiB of arrays (shared references); not a PhysTwin case file")
            sizes[key] = (n, b)
            continue
        if key in sizes:
            continue
        if key in open_:
            raise PhysTwinFormatError(f"{source}: {where or 'value'} contains itself; "
                                      "not a PhysTwin case file")
        if depth >= MAX_DEPTH:
            raise PhysTwinFormatError(f"{source}: {where[:80] or 'value'}...: nested more than {MAX_DEPTH} "
                                      "deep; not a PhysTwin case file")
        open_.add(key)
        stack.append((value, where, depth, True))
        stack.extend((v, w, depth + 1, False) for v, w in items if id(v) not in sizes)


def _scan_opcodes(data: bytes, source: str) -> None:
    """Refuse a pickle stream whose memo slots are far beyond its length before unpickling it (the
    unpickler sizes its memo to the largest slot: a 1 kB file could ask for gigabytes)."""
    import pickletools

    try:
        for count, (op, arg, _) in enumerate(pickletools.genops(data)):
            if op.name in ("PUT", "BINPUT", "LONG_BINPUT", "GET", "BINGET", "LONG_BINGET") and (
                not isinstance(arg, int) or not 0 <= arg <= count
            ):
                raise PhysTwinFormatError(f"{source}: memo slot {arg!r:.40} at opcode {count} is out of "
                                          "range; not a pickle written by pickle.dump")
    except PhysTwinFormatError:
        raise
    except Exception as exc:  # noqa: BLE001 - malformed streams raise many types
        raise PhysTwinFormatError(f"{source}: not a readable pickle ({type(exc).__name__}: {exc})") from None


def _unpickle(data: bytes, source: str, what: str, **kw) -> object:
    _scan_opcodes(data, source)
    try:
        obj = _RestrictedUnpickler(io.BytesIO(data), source=source, **kw).load()
    except PhysTwinFormatError:
        raise
    except Exception as exc:  # noqa: BLE001 - malformed streams raise many types
        raise PhysTwinFormatError(f"{source}: not a readable {what} ({type(exc).__name__}: {exc})") from None
    _check_plain(obj, source)
    return obj


def load_pickle(path) -> object:
    """Safely read a pickle of numpy arrays and plain values (e.g. final_data.pkl, optimal_params.pkl)."""
    path = Path(path)
    try:
        if path.stat().st_size > MAX_BYTES:
            raise PhysTwinFormatError(f"{path}: larger than {MAX_BYTES >> 20} MiB; not a PhysTwin case file")
        data = path.read_bytes()
    except OSError as exc:
        raise PhysTwinFormatError(f"{path}: cannot read ({exc})") from exc
    return _unpickle(data, str(path), "pickle")


def load_torch_zip(path) -> object:
    """Safely read a `torch.save` zip archive (tensors come back as numpy arrays; torch not needed). A
    damaged archive or one whose records inflate beyond what its tensors need is a PhysTwinFormatError."""
    path = Path(path)
    if not zipfile.is_zipfile(path):
        raise PhysTwinFormatError(
            f"{path}: not a torch zip archive (the legacy pre-1.6 format is not read); re-save it with "
            "torch.save in a current torch"
        )
    try:
        with zipfile.ZipFile(path) as zf:
            names = zf.namelist()
            pkl = [n for n in names if n.endswith("data.pkl") and n.count("/") == 1]
            if len(pkl) != 1:
                raise PhysTwinFormatError(f"{path}: expected one PREFIX/data.pkl in the archive, found {pkl}")
            prefix = pkl[0][: -len("data.pkl")]
            byteorder = "little"
            if prefix + "byteorder" in names:
                with zf.open(prefix + "byteorder") as f:
                    byteorder = f.read(16).decode("ascii", "replace").strip()
                if byteorder not in ("little", "big"):
                    raise PhysTwinFormatError(f"{path}: unknown byteorder {byteorder!r}")
            with zf.open(pkl[0]) as f:
                data = f.read(MAX_TORCH_PICKLE + 1)
            if len(data) > MAX_TORCH_PICKLE:
                raise PhysTwinFormatError(f"{path}: {pkl[0]} inflates beyond {MAX_TORCH_PICKLE >> 20} MiB")
            return _unpickle(data, str(path), "torch archive", records=_Records(zf, prefix, str(path)),
                             byteorder=byteorder)
    except PhysTwinFormatError:
        raise
    except Exception as exc:  # noqa: BLE001 - a damaged archive (BadZipFile, zlib.error, EOFError, ...)
        raise PhysTwinFormatError(
            f"{path}: a damaged zip archive ({type(exc).__name__}: {exc}); re-save it with torch.save"
        ) from None


# ------------------------------------------------------------------------------------------------
# writing (export)


@dataclass(frozen=True)
class _Global:
    """A reference to a global written as a GLOBAL opcode (never imported here)."""

    module: str
    name: str

    def __call__(self, *args):  # pickle requires reduce functions to be callable
        raise TypeError(f"{self.module}.{self.name} is a pickle reference, not callable here")


class _TorchPickler(pickle._Pickler):
    """Protocol-2 pickler writing numpy arrays as torch tensors (storages as persistent records)."""

    dispatch = dict(pickle._Pickler.dispatch)

    def __init__(self, file):
        super().__init__(file, protocol=2)
        self.records: list[bytes] = []

    def _save_global_ref(self, obj):
        self.write(pickle.GLOBAL + f"{obj.module}\n{obj.name}\n".encode("ascii"))

    dispatch[_Global] = _save_global_ref

    def persistent_id(self, obj):
        if isinstance(obj, _Storage):
            names = {v: k for k, v in _TORCH_STORAGES.items() if v is not None}
            key = str(len(self.records))
            little = obj.data.dtype.newbyteorder("<")
            self.records.append(np.ascontiguousarray(obj.data, dtype=little).tobytes())
            return ("storage", _Global("torch", names[obj.data.dtype.newbyteorder("<")]), key, "cpu",
                    int(obj.data.size))
        return None

    def reducer_override(self, obj):
        if isinstance(obj, np.ndarray):
            a = np.ascontiguousarray(obj)
            if a.dtype.newbyteorder("<") not in {v for v in _TORCH_STORAGES.values() if v is not None}:
                raise ValueError(f"cannot write a {a.dtype} array as a torch tensor")
            stride = tuple(int(s) // a.itemsize for s in a.strides) if a.ndim else ()
            return (_Global("torch._utils", "_rebuild_tensor_v2"),
                    (_Storage(a.reshape(-1)), 0, tuple(a.shape), stride, False, OrderedDict()))
        return NotImplemented


def save_torch_zip(obj, path, *, prefix: str | None = None) -> None:
    """Write `obj` (plain values and numpy arrays, which become tensors) in torch's zip layout."""
    path = Path(path)
    prefix = prefix or re.sub(r"[^A-Za-z0-9_]", "_", path.stem) or "archive"
    buf = io.BytesIO()
    pk = _TorchPickler(buf)
    pk.dump(obj)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as zf:
        zf.writestr(f"{prefix}/data.pkl", buf.getvalue())
        zf.writestr(f"{prefix}/byteorder", "little")
        for i, raw in enumerate(pk.records):
            zf.writestr(f"{prefix}/data/{i}", raw)
        zf.writestr(f"{prefix}/version", "3\n")


# ------------------------------------------------------------------------------------------------
# a case


@dataclass
class PhysTwinCase:
    """The arrays and scalars of a trained case, as read (PhysTwin's own frame)."""

    final_data: dict[str, np.ndarray]
    optimal_params: dict[str, float]
    checkpoint: dict[str, object]
    sources: dict[str, str] = field(default_factory=dict)

    @property
    def structure_points(self) -> np.ndarray:
        """Particles in PhysTwin's order: tracked points (first frame), extra surface, interior (float32)."""
        fd = self.final_data
        return np.concatenate(
            [fd["object_points"][0], fd["surface_points"], fd["interior_points"]], axis=0
        ).astype(np.float32)

    @property
    def num_object_springs(self) -> int:
        return int(self.checkpoint["num_object_springs"])

    def scalar(self, key: str) -> float:
        """A contact scalar from the checkpoint (trained), else from optimal_params."""
        v = self.checkpoint.get(key, self.optimal_params.get(key))
        return float(np.asarray(v).reshape(-1)[0])


def _latest_checkpoint(folder: Path) -> Path | None:
    found = []
    for d in (folder, folder / "train"):
        for p in d.glob("best_*.pth"):
            m = re.fullmatch(r"best_(\d+)\.pth", p.name)
            if m:
                found.append((int(m.group(1)), p))
    return max(found)[1] if found else None


def find_case_files(case_dir, *, final_data=None, optimal_params=None, checkpoint=None) -> dict[str, Path]:
    """The three files of a case folder (flat: final_data.pkl, optimal_params.pkl, best_*.pth or
    train/best_*.pth, the highest epoch); explicit paths override the search."""
    case_dir = Path(case_dir)
    out = {
        "final_data": Path(final_data) if final_data else case_dir / "final_data.pkl",
        "optimal_params": Path(optimal_params) if optimal_params else case_dir / "optimal_params.pkl",
    }
    ck = Path(checkpoint) if checkpoint else _latest_checkpoint(case_dir)
    if ck is None:
        raise FileNotFoundError(
            f"{case_dir}: no best_EPOCH.pth (or train/best_EPOCH.pth); pass the checkpoint path explicitly"
        )
    out["checkpoint"] = ck
    for name, p in out.items():
        if not p.is_file():
            raise FileNotFoundError(f"PhysTwin case: {name} file not found: {p}")
    return out


def _require(d, keys, source: str):
    if not isinstance(d, dict):
        raise PhysTwinFormatError(f"{source}: expected a dict at the top level, got {type(d).__name__}")
    missing = [k for k in keys if k not in d]
    if missing:
        raise PhysTwinFormatError(f"{source}: missing field(s) {missing}; is this a PhysTwin case file?")


def read_case(case_dir, **paths) -> PhysTwinCase:
    """Read and validate a trained case (see `find_case_files` for the layout)."""
    files = find_case_files(case_dir, **paths)
    fd = load_pickle(files["final_data"])
    _require(fd, FINAL_KEYS, str(files["final_data"]))
    op = load_pickle(files["optimal_params"])
    _require(op, OPTIMAL_KEYS, str(files["optimal_params"]))
    ck = load_torch_zip(files["checkpoint"])
    _require(ck, CHECKPOINT_KEYS, str(files["checkpoint"]))
    src = str(files["final_data"])
    final = {k: np.asarray(fd[k]) for k in FINAL_KEYS}
    op_ = final["object_points"]
    if op_.ndim != 3 or op_.shape[2] != 3 or op_.shape[0] < 1:
        raise PhysTwinFormatError(f"{src}: object_points must have shape (F, N, 3), got {op_.shape}")
    f, n = op_.shape[:2]
    shapes = {
        "object_colors": (f, n, 3), "object_visibilities": (f, n), "object_motions_valid": (f, n),
    }
    for k, shp in shapes.items():
        if final[k].shape != shp:
            raise PhysTwinFormatError(f"{src}: {k} must have shape {shp}, got {final[k].shape}")
    cp = final["controller_points"]
    if cp.ndim != 3 or cp.shape[0] != f or cp.shape[2] != 3:
        raise PhysTwinFormatError(f"{src}: controller_points must have shape ({f}, K, 3), got {cp.shape}")
    for k in ("surface_points", "interior_points"):
        final[k] = final[k].reshape(-1, 3) if final[k].size == 0 else final[k]
        if final[k].ndim != 2 or final[k].shape[1] != 3:
            raise PhysTwinFormatError(f"{src}: {k} must have shape (P, 3), got {final[k].shape}")
    for k in ("object_points", "controller_points", "surface_points", "interior_points"):
        if not np.all(np.isfinite(final[k])):
            raise PhysTwinFormatError(f"{src}: {k} contains NaN or inf")
    spring_y = np.asarray(ck["spring_Y"], dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(spring_y)) or np.any(spring_y <= 0):
        raise PhysTwinFormatError(f"{files['checkpoint']}: spring_Y must be finite and > 0")
    ck = dict(ck)
    ck["spring_Y"] = np.asarray(ck["spring_Y"]).reshape(-1)
    return PhysTwinCase(final, {k: op[k] for k in op}, ck, {k: str(v) for k, v in files.items()})


# ------------------------------------------------------------------------------------------------
# case <-> twinbench object


@dataclass
class ImportedObject:
    """A PhysTwin case as a twinbench object (z-up object frame) with its simulation settings."""

    particles: np.ndarray  # (P, 3) float32, object frame
    springs: np.ndarray  # (M, 2) int32, PhysTwin order
    rest_lengths: np.ndarray  # (M,) float32
    spring_Y: np.ndarray  # (M,) float32
    sim: dict  # SimParams fields
    frame: np.ndarray  # (4, 4) PhysTwin frame -> object frame
    controller_springs: np.ndarray  # (C, 2) (controller index, particle index), PhysTwin order
    controller_spring_Y: np.ndarray  # (C,)
    case: PhysTwinCase


def phystwin_springs(points, radius: float, max_neighbours: int) -> np.ndarray:
    """PhysTwin's object springs (its order): the radius rule with the query point counted among the
    `max_neighbours` Open3D returns (see the module docstring)."""
    from twinbench.physics import radius_springs

    if int(max_neighbours) < 2:
        raise ValueError(f"object_max_neighbours must be >= 2, got {max_neighbours}")
    return radius_springs(np.asarray(points, dtype=np.float64), float(radius), int(max_neighbours) - 1)


def controller_springs(points, controllers, radius: float, max_neighbours: int) -> np.ndarray:
    """PhysTwin's controller springs: (controller index, particle index), nearest first per controller."""
    from scipy.spatial import cKDTree

    from twinbench.physics.model import _sorted_neighbours

    pts = np.asarray(points, dtype=np.float64)
    ctl = np.asarray(controllers, dtype=np.float64).reshape(-1, 3)
    rows = []
    for c, nb in enumerate(_sorted_neighbours(cKDTree(pts), pts, ctl, float(radius), int(max_neighbours),
                                              exclude_self=False)):
        rows += [(c, int(j)) for j in nb]
    return np.asarray(rows, dtype=np.int64).reshape(-1, 2)


def phystwin_config(optimal_params: dict) -> dict[str, float | int]:
    """The stage-1 scalars as PhysTwin's config holds them after loading: int() for the fields whose
    default is an int (`PHYSTWIN_INT_FIELDS`), float for the rest."""
    out: dict[str, float | int] = {}
    for k in OPTIMAL_KEYS:
        v = np.asarray(optimal_params[k]).reshape(-1)[0].item()
        out[k] = int(v) if k in PHYSTWIN_INT_FIELDS else float(v)
    return out


def import_case(
    case: PhysTwinCase, *, reverse_z: bool = True, self_collision: bool = False
) -> ImportedObject:
    """Rebuild the case's springs in PhysTwin's order, check them against the checkpoint, and express
    the object in twinbench's z-up frame with the simulation settings it was trained with."""
    op = phystwin_config(case.optimal_params)
    pts = case.structure_points
    springs = phystwin_springs(pts, op["object_radius"], op["object_max_neighbours"])
    ctrl = controller_springs(pts, case.final_data["controller_points"][0], op["controller_radius"],
                              op["controller_max_neighbours"])
    y = np.asarray(case.checkpoint["spring_Y"], dtype=np.float32)
    src = case.sources.get("checkpoint", "checkpoint")
    if len(springs) != case.num_object_springs or len(springs) + len(ctrl) != len(y):
        raise PhysTwinFormatError(
            f"{src}: the springs rebuilt by PhysTwin's rule ({len(springs)} object + {len(ctrl)} controller) "
            f"do not match the checkpoint (num_object_springs={case.num_object_springs}, "
            f"{len(y)} spring_Y values); the case files come from different runs or settings"
        )
    frame = FLIP_Z.copy() if reverse_z else np.eye(4)
    p64 = pts.astype(np.float64)
    rest = np.linalg.norm(p64[springs[:, 1]] - p64[springs[:, 0]], axis=1).astype(np.float32)
    obj_pts = (p64 @ frame[:3, :3].T).astype(np.float32)
    sim = {
        "dashpot_damping": float(op["dashpot_damping"]),  # int() by PhysTwin's loader
        "drag_damping": float(op["drag_damping"]),
        "ground_restitution": case.scalar("collide_elas"),
        "ground_friction": case.scalar("collide_fric"),
        "object_restitution": case.scalar("collide_object_elas"),
        "object_friction": case.scalar("collide_object_fric"),
        "collision_dist": float(op["collision_dist"]),
        "self_collision": bool(self_collision),
        "collision_exclusion": "none",
        "spring_Y_min": 0.0,
        "spring_Y_max": 1e5,
    }
    n_obj = len(springs)
    return ImportedObject(
        particles=obj_pts, springs=springs.astype(np.int32), rest_lengths=rest, spring_Y=y[:n_obj],
        sim=sim, frame=frame, controller_springs=ctrl, controller_spring_Y=y[n_obj:], case=case,
    )


def write_case(out_dir, final_data: dict, optimal_params: dict, checkpoint: dict, *, epoch: int = 0) -> dict:
    """Write a flat case folder: final_data.pkl, optimal_params.pkl (plain pickles of numpy arrays and
    floats) and train/best_EPOCH.pth (torch zip layout). Returns the written paths."""
    out = Path(out_dir)
    (out / "train").mkdir(parents=True, exist_ok=True)
    _require(final_data, FINAL_KEYS, "final_data")
    _require(optimal_params, OPTIMAL_KEYS, "optimal_params")
    _require(checkpoint, CHECKPOINT_KEYS, "checkpoint")
    paths = {"final_data": out / "final_data.pkl", "optimal_params": out / "optimal_params.pkl",
             "checkpoint": out / "train" / f"best_{int(epoch)}.pth"}
    with open(paths["final_data"], "wb") as f:
        pickle.dump({k: np.asarray(final_data[k]) for k in FINAL_KEYS}, f, protocol=4)
    with open(paths["optimal_params"], "wb") as f:
        pickle.dump({k: optimal_params[k] for k in OPTIMAL_KEYS}, f, protocol=4)
    ck = {"epoch": int(epoch), **checkpoint}
    save_torch_zip(ck, paths["checkpoint"])
    return paths


def case_metadata(case: PhysTwinCase, imported: ImportedObject, reverse_z: bool) -> dict:
    """JSON-ready scalars an export needs besides the arrays."""
    ck = {k: float(np.asarray(case.checkpoint[k]).reshape(-1)[0]) for k in
          ("collide_elas", "collide_fric", "collide_object_elas", "collide_object_fric")}
    return {
        "optimal_params": {k: (int(v) if k.endswith("max_neighbours") else float(v))
                           for k, v in case.optimal_params.items() if k in OPTIMAL_KEYS},
        "checkpoint": {**ck, "num_object_springs": case.num_object_springs,
                       "epoch": int(case.checkpoint.get("epoch", 0))},
        "reverse_z": bool(reverse_z),
        "frame": imported.frame.tolist(),
        "sources": case.sources,
    }


def case_arrays(case: PhysTwinCase) -> dict[str, np.ndarray]:
    """npz-ready arrays of a case (final_data fields + the full spring_Y), PhysTwin frame."""
    return {**{f"final_{k}": v for k, v in case.final_data.items()},
            "checkpoint_spring_Y": np.asarray(case.checkpoint["spring_Y"])}


def case_from_arrays(arrays: dict, meta: dict) -> tuple[dict, dict, dict, int]:
    """(final_data, optimal_params, checkpoint, epoch) back from `case_arrays` + `case_metadata`."""
    final = {k: np.asarray(arrays[f"final_{k}"]) for k in FINAL_KEYS}
    ck_meta = dict(meta["checkpoint"])
    epoch = int(ck_meta.pop("epoch", 0))
    ck = {"spring_Y": np.asarray(arrays["checkpoint_spring_Y"], dtype=np.float32),
          "num_object_springs": int(ck_meta.pop("num_object_springs"))}
    for k, v in ck_meta.items():
        ck[k] = np.asarray([v], dtype=np.float32)
    return final, dict(meta["optimal_params"]), ck, epoch


# ------------------------------------------------------------------------------------------------
# files: a twin object folder carrying its case


def import_case_to_object(case_dir, out, *, name: str = "object", final_data=None, optimal_params=None,
                          checkpoint=None, reverse_z: bool = True, self_collision: bool = False,
                          gaussians=None) -> ImportedObject:
    """`twinbench import-phystwin`: read and import a case (`read_case`, `import_case`) and write it as a
    twin object folder (`write_imported_object`); `gaussians`: an optional 3DGS file in the case's frame."""
    from twinbench.gaussians.io import load_gaussians

    case = read_case(case_dir, final_data=final_data, optimal_params=optimal_params, checkpoint=checkpoint)
    imp = import_case(case, reverse_z=reverse_z, self_collision=self_collision)
    g = None if gaussians is None else load_gaussians(gaussians).transform(imp.frame)
    write_imported_object(out, name, imp, g, case_arrays(case), case_metadata(case, imp, reverse_z))
    return imp


def write_imported_object(out, name: str, imp: ImportedObject, gaussians, arrays: dict, meta: dict) -> None:
    """object.json + arrays (`twinbench.twin.save_object`), and phystwin.npz / phystwin.json: the case's
    tracking data and scalars, for `export_object_to_case`."""
    from twinbench.construct._json import write_json
    from twinbench.twin import ObjectSpec, save_object

    obj = ObjectSpec(name, imp.particles, springs=imp.springs, rest_lengths=imp.rest_lengths,
                     spring_Y=imp.spring_Y.astype(np.float64), mass=1.0, gaussians=gaussians, binding="lbs")
    save_object(obj, out, sim=imp.sim)
    np.savez(Path(out) / "phystwin.npz", **arrays)
    write_json(Path(out) / "phystwin.json", meta)


def export_object_to_case(object_dir, out) -> dict:
    """`twinbench export-phystwin`: write an object folder written by `write_imported_object` back as a
    PhysTwin case folder (`write_case`); returns the written paths."""
    object_dir = Path(object_dir)
    with np.load(object_dir / "phystwin.npz", allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    final, op, ck, epoch = case_from_arrays(arrays, json.loads((object_dir / "phystwin.json").read_text()))
    return write_case(out, final, op, ck, epoch=epoch)


def sysid_data_from_final_data(path, *, reverse_z: bool = True, validation_frames: int | None = None):
    """System-identification input (`twinbench.physics.sysid_data.SysIdData`) from a PhysTwin case's
    training data `final_data.pkl`, read through the restricted loader.

    Particles are PhysTwin's structure points (tracked points of frame 0, then the surface and interior
    completions); the tracked points are the first N particles, observed in every frame where visible
    and trusted where `object_motions_valid`; the Chamfer term matches the observed surface only (not the
    interior completions); control points are `controller_points`. `reverse_z` turns PhysTwin's frame
    z up, as `import_case` does. `validation_frames` defaults to the last fifth of the frames."""
    from twinbench.physics.sysid_data import SysIdData

    path = Path(path)
    if path.is_dir():
        path = path / "final_data.pkl"
    fd = load_pickle(path)
    keys = ("object_points", "object_visibilities", "object_motions_valid", "controller_points",
            "surface_points", "interior_points")
    _require(fd, keys, str(path))
    rot = (FLIP_Z if reverse_z else np.eye(4))[:3, :3]

    def points(key):
        arr = np.asarray(fd[key], dtype=np.float64)
        if key in ("surface_points", "interior_points") and arr.size == 0:
            arr = arr.reshape(0, 3)
        if arr.shape[-1:] != (3,):
            raise PhysTwinFormatError(f"{path}: {key} must hold 3D points, got shape {arr.shape}")
        return arr @ rot.T

    obs, surface, interior = points("object_points"), points("surface_points"), points("interior_points")
    if obs.ndim != 3:
        raise PhysTwinFormatError(f"{path}: object_points must have shape (F, N, 3), got {obs.shape}")
    n_frames, n = obs.shape[:2]
    return SysIdData(
        particles=np.concatenate([obs[0], surface, interior]), observed=obs,
        visibility=np.asarray(fd["object_visibilities"]).astype(bool), tracked_indices=np.arange(n),
        tracked=obs, motion_valid=np.asarray(fd["object_motions_valid"]).astype(bool),
        controls=points("controller_points"),
        validation_frames=max(1, n_frames // 5) if validation_frames is None else int(validation_frames),
        name=path.parent.name or "phystwin", surface_indices=np.arange(n + len(surface)), source=str(path),
    )
