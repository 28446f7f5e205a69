"""3DGS file formats: INRIA `.ply` (binary / ASCII; SuperSplat's compressed .ply read), antimatter15
`.splat`, Niantic `.spz` (v2, v3).

`load_gaussians(path)` / `save_gaussians(cloud, path)` dispatch on the extension. Every reader validates
its input and raises `GaussianFileError` (a ValueError) naming the file and the problem.
Axes: a GaussianCloud uses the INRIA .ply axes as stored. `.spz` stores RUB axes (its spec), so its
reader and writer convert RUB <-> RDF (y, z negated; the same convention as Niantic's library with
`to/from = RDF`). `.splat` and `.ply` are read as-is; a `.ply` may also be SuperSplat's compressed
layout (read only). .spz extension records and the uncompressed NGSP (v4) container are rejected with
clear errors.
"""

from __future__ import annotations

import gzip
import re
import struct
import warnings
import zlib
from pathlib import Path

import numpy as np

from twinbench.errors import InputError
from twinbench.gaussians.cloud import SH_C0, GaussianCloud
from twinbench.gaussians.sh import sh_rotation_matrices


class GaussianFileError(InputError):
    """A Gaussian file is missing, truncated, malformed or holds invalid values."""

    def __init__(self, path, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = str(path)
        self.problem = problem


_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
_REST_FOR_DEGREE = {0: 0, 9: 1, 24: 2, 45: 3}
_REQUIRED = [
    "x",
    "y",
    "z",
    "f_dc_0",
    "f_dc_1",
    "f_dc_2",
    "opacity",
    "scale_0",
    "scale_1",
    "scale_2",
    "rot_0",
    "rot_1",
    "rot_2",
    "rot_3",
]
_IGNORED = {"nx", "ny", "nz"}


MAX_GAUSSIANS = 50_000_000
"""Most Gaussians a file may declare (a large room scan holds ~5-10 million); more is refused before any
allocation. Pass `max_gaussians=` to `load_gaussians` to change it."""
LOG_SCALE_RANGE = (-30.0, 20.0)
"""Accepted log-scales (scale from 9e-14 m to 4.9e8 m); anything outside is a corrupt value that would
render as NaN/inf (an all-black image)."""


def _check_count(path, n: int, max_gaussians: int) -> None:
    if n > max_gaussians:
        raise GaussianFileError(
            path, f"declares {n} Gaussians, over the limit of {max_gaussians} (corrupt header?); "
            "pass max_gaussians= to load_gaussians to raise the limit"
        )


def _check_log_scales(path, log_scales: np.ndarray) -> None:
    lo, hi = LOG_SCALE_RANGE
    bad = (log_scales < lo) | (log_scales > hi)
    if np.any(bad):
        rows = np.flatnonzero(bad.reshape(len(log_scales), -1).any(axis=1))
        raise GaussianFileError(
            path,
            f"{len(rows)} Gaussians have a log-scale outside [{lo:g}, {hi:g}] (first at Gaussian {rows[0]}: "
            f"{log_scales[rows[0]].tolist()}); corrupt values, clean the file",
        )


def _check_finite(path, name: str, arr: np.ndarray) -> None:
    """Every value finite, also once stored as float32 (an ASCII 1e308 is finite only in float64)."""
    with np.errstate(over="ignore"):
        bad = ~np.isfinite(arr) | ~np.isfinite(np.asarray(arr).astype(np.float32))
    if np.any(bad):
        rows = np.flatnonzero(bad.reshape(len(arr), -1).any(axis=1))
        raise GaussianFileError(
            path,
            f"{name} has {len(rows)} non-finite (NaN/inf) or float32-overflowing values, first at "
            f"Gaussian {rows[0]}; clean the file (e.g. drop those Gaussians)",
        )


# ----- PLY ----------------------------------------------------------------------------------------
def _parse_ply_header(path, data: bytes):
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise GaussianFileError(
            path, "not a PLY file, or its header is truncated (missing 'ply' magic or 'end_header')"
        )
    nl = data.find(b"\n", end)
    if nl < 0:
        raise GaussianFileError(path, "truncated PLY header (no newline after 'end_header')")
    header = data[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[list] = []  # [name, count, [(prop, dtype or None for list)]]
    for line in header[1:]:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            fmt = tok[1] if len(tok) > 1 else None
        elif tok[0] == "element":
            if len(tok) != 3 or not re.fullmatch(r"\d+", tok[2]):
                raise GaussianFileError(path, f"malformed header line {line!r}")
            elements.append([tok[1], int(tok[2]), []])
        elif tok[0] == "property":
            if not elements:
                raise GaussianFileError(path, f"property before any element: {line!r}")
            if len(tok) >= 5 and tok[1] == "list":
                elements[-1][2].append((tok[-1], None))
            elif len(tok) == 3 and tok[1] in _PLY_TYPES:
                elements[-1][2].append((tok[2], _PLY_TYPES[tok[1]]))
            else:
                raise GaussianFileError(path, f"unsupported property line {line!r}")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise GaussianFileError(path, f"unknown PLY format {fmt!r}")
    return fmt, elements, nl + 1


def _read_ply(path: Path, max_gaussians: int = MAX_GAUSSIANS) -> GaussianCloud:
    data = path.read_bytes()
    fmt, elements, body = _parse_ply_header(path, data)
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise GaussianFileError(path, "no 'vertex' element in the PLY header")
    vi = names.index("vertex")
    count, props = elements[vi][1], elements[vi][2]
    _check_count(path, count, max_gaussians)
    for name, cnt, _ in elements:
        if cnt > len(data):  # every element row takes at least one byte
            raise GaussianFileError(path, f"element {name!r} declares {cnt} rows in a {len(data)}-byte file")
    prop_names = [p for p, _ in props]
    if "packed_position" in prop_names or "chunk" in names:
        column = _read_compressed_ply(path, data, fmt, elements, body)
        rest = [p for p in column if p.startswith("f_rest_")]
        return _cloud_from_columns(path, count, column, rest)
    if any(t is None for _, t in props):
        raise GaussianFileError(path, "list properties in the 'vertex' element are not supported")
    missing = [p for p in _REQUIRED if p not in prop_names]
    if missing:
        raise GaussianFileError(
            path, f"missing vertex properties {missing}; an INRIA 3DGS .ply needs {_REQUIRED} (+ f_rest_*)"
        )
    rest = sorted((p for p in prop_names if p.startswith("f_rest_")), key=lambda p: int(p[7:]))
    if len(rest) not in _REST_FOR_DEGREE or rest != [f"f_rest_{i}" for i in range(len(rest))]:
        raise GaussianFileError(
            path,
            f"found {len(rest)} f_rest_* properties; expected f_rest_0..N-1 with "
            "N in (0, 9, 24, 45) for SH degree 0..3",
        )
    extra = [p for p in prop_names if p not in _REQUIRED and p not in rest and p not in _IGNORED]
    if extra:
        warnings.warn(f"{path}: ignoring extra vertex properties {extra}", stacklevel=3)
    if fmt == "ascii":
        lines = data[body:].decode("ascii", errors="replace").splitlines()
        skip = sum(e[1] for e in elements[:vi])
        rows = [ln for ln in lines if ln.strip()][skip:]
        after = sum(e[1] for e in elements[vi + 1 :])
        if len(rows) != count + after:
            raise GaussianFileError(
                path,
                f"header declares {count} vertices but the body has "
                f"{len(rows) - after} rows (truncated or wrong count)",
            )
        try:
            table = np.array(" ".join(rows[:count]).split(), dtype=np.float64)
        except ValueError as exc:
            raise GaussianFileError(path, f"non-numeric value in vertex data ({exc})") from None
        if table.size != count * len(props):
            raise GaussianFileError(path, f"vertex rows do not all have {len(props)} values")
        table = table.reshape(count, len(props))
        column = {p: table[:, i] for i, p in enumerate(prop_names)}
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        offset = body
        for name, cnt, eprops in elements[:vi]:
            if any(t is None for _, t in eprops):
                raise GaussianFileError(
                    path, f"cannot skip element {name!r} with list properties before 'vertex'"
                )
            offset += cnt * np.dtype([(p, order + t) for p, t in eprops]).itemsize
        dtype = np.dtype([(p, order + t) for p, t in props])
        need = count * dtype.itemsize
        available = len(data) - offset
        if available < need:
            raise GaussianFileError(
                path,
                f"truncated: header declares {count} vertices ({need} bytes) but only "
                f"{max(available, 0)} bytes follow",
            )
        if vi == len(elements) - 1 and available > need:
            raise GaussianFileError(
                path,
                f"{available - need} unexpected bytes after {count} vertices "
                "(wrong vertex count in the header?)",
            )
        arr = np.frombuffer(data, dtype=dtype, count=count, offset=offset)
        column = {p: arr[p].astype(np.float64) for p in prop_names}
    return _cloud_from_columns(path, count, column, rest)


def _cloud_from_columns(path, count: int, column: dict[str, np.ndarray], rest: list[str]) -> GaussianCloud:
    """A checked GaussianCloud from an INRIA .ply's vertex columns (`rest`: the f_rest_* names)."""
    k1 = _REST_FOR_DEGREE[len(rest)] * (_REST_FOR_DEGREE[len(rest)] + 2)  # K - 1
    means = np.stack([column["x"], column["y"], column["z"]], 1)
    sh = np.zeros((count, k1 + 1, 3))
    sh[:, 0] = np.stack([column[f"f_dc_{c}"] for c in range(3)], 1)
    for c in range(3):
        for j in range(k1):
            sh[:, 1 + j, c] = column[f"f_rest_{c * k1 + j}"]
    quats = np.stack([column[f"rot_{i}"] for i in range(4)], 1)
    log_scales = np.stack([column[f"scale_{i}"] for i in range(3)], 1)
    opac = column["opacity"]
    for name, arr in (
        ("position (x, y, z)", means),
        ("f_dc/f_rest", sh),
        ("rot_*", quats),
        ("scale_*", log_scales),
        ("opacity", opac),
    ):
        _check_finite(path, name, arr)
    _check_quats(path, quats)
    _check_log_scales(path, log_scales)
    return GaussianCloud(means, quats, log_scales, opac, sh)


# SuperSplat's compressed .ply (PlayCanvas): Gaussians in chunks of 256, each chunk with float32 bounds
# (min_/max_ x, y, z; min_/max_scale_ x, y, z of the log-scales; optionally min_/max_ r, g, b), each
# Gaussian four uint32: position and log-scale as 11/10/11-bit fractions of the chunk's bounds (x in the
# top bits), colour and opacity as 8-bit r, g, b, a (a = sigmoid(opacity); r, g, b the DC colour, or a
# fraction of the chunk's colour bounds), the rotation as its largest component's slot (top 2 bits, of
# rot_0..rot_3) and the other three in slot order, 10 bits each over +-1/sqrt(2). An optional `sh`
# element holds f_rest_* as bytes over [-4, 4].
_CHUNK_BOUNDS = [f"{m}_{a}" for m in ("min", "max") for a in ("x", "y", "z")] + [
    f"{m}_scale_{a}" for m in ("min", "max") for a in ("x", "y", "z")]
_CHUNK_COLOURS = [f"{m}_{c}" for m in ("min", "max") for c in ("r", "g", "b")]
_PACKED = ["packed_position", "packed_rotation", "packed_scale", "packed_color"]


def _read_compressed_ply(path, data: bytes, fmt: str, elements: list, body: int) -> dict[str, np.ndarray]:
    """The INRIA vertex columns of a SuperSplat compressed .ply (layout above)."""
    if fmt != "binary_little_endian":
        raise GaussianFileError(path, f"a compressed PLY (SuperSplat 'chunk' layout) is binary little "
                                      f"endian; this one is {fmt}")
    names = [e[0] for e in elements]
    arrays, offset = {}, body
    for name, cnt, eprops in elements:
        lists = any(t is None for _, t in eprops)
        if name not in ("chunk", "vertex", "sh") or names.count(name) > 1 or lists:
            raise GaussianFileError(path, f"element {name!r}: a compressed PLY (SuperSplat 'chunk' layout) "
                                          "holds one each of 'chunk', 'vertex' and optionally 'sh', with "
                                          "scalar properties")
        dtype = np.dtype([(p, "<" + t) for p, t in eprops])
        need, left = cnt * dtype.itemsize, len(data) - offset
        if left < need:
            raise GaussianFileError(path, f"truncated: element {name!r} declares {cnt} rows ({need} bytes) "
                                          f"but only {left} follow")
        arrays[name] = np.frombuffer(data, dtype=dtype, count=cnt, offset=offset)
        offset += cnt * dtype.itemsize
    if offset != len(data):
        raise GaussianFileError(path, f"{len(data) - offset} unexpected bytes after the compressed PLY's "
                                      "elements (wrong counts in the header?)")
    chunk, vertex = arrays.get("chunk"), arrays.get("vertex")
    if chunk is None:
        raise GaussianFileError(path, "a compressed PLY (packed_* properties) needs its 'chunk' element")
    n = len(vertex)
    colours = "min_r" in chunk.dtype.names  # per-chunk colour bounds (newer writers)
    want = {"chunk": _CHUNK_BOUNDS + (_CHUNK_COLOURS if colours else []),
            "vertex": _PACKED}
    for name, props in want.items():
        have = arrays[name].dtype
        bad = [p for p in props if p not in have.names
               or have[p] != np.dtype("<f4" if name == "chunk" else "<u4")]
        if bad or len(have.names) != len(props):
            kind = "float" if name == "chunk" else "uint"
            raise GaussianFileError(path, f"compressed PLY element {name!r} needs exactly the {kind} "
                                          f"properties {props}; got {list(have.names)}")
    if len(chunk) != (n + 255) // 256:
        raise GaussianFileError(path, f"{len(chunk)} chunks for {n} Gaussians; a compressed PLY has one "
                                      f"chunk per 256 Gaussians ({(n + 255) // 256})")
    of_chunk = np.arange(n) // 256

    def unorm(word, shift: int, bits: int) -> np.ndarray:
        top = (1 << bits) - 1
        return ((word >> np.uint32(shift)) & np.uint32(top)).astype(np.float64) / top

    def lerp(name: str, t: np.ndarray) -> np.ndarray:
        """Each Gaussian's fraction t between its chunk's min_NAME and max_NAME."""
        lo = chunk[f"min_{name}"].astype(np.float64)[of_chunk]
        return lo * (1.0 - t) + chunk[f"max_{name}"].astype(np.float64)[of_chunk] * t

    column = {}
    pos, scale, colour = vertex["packed_position"], vertex["packed_scale"], vertex["packed_color"]
    for k, (axis, shift, bits) in enumerate((("x", 21, 11), ("y", 11, 10), ("z", 0, 11))):
        column[axis] = lerp(axis, unorm(pos, shift, bits))
        column[f"scale_{k}"] = lerp(f"scale_{axis}", unorm(scale, shift, bits))
    for k, ch in enumerate("rgb"):
        v = unorm(colour, 24 - 8 * k, 8)
        if colours:
            v = lerp(ch, v)
        column[f"f_dc_{k}"] = (v - 0.5) / SH_C0
    column["opacity"] = _logit(unorm(colour, 0, 8))
    rot = vertex["packed_rotation"]
    small = np.stack([(unorm(rot, shift, 10) - 0.5) * np.sqrt(2.0) for shift in (20, 10, 0)], axis=1)
    largest = np.sqrt(np.maximum(0.0, 1.0 - (small**2).sum(axis=1)))
    which = (rot >> np.uint32(30)).astype(np.intp)
    quats = np.empty((n, 4))
    for slot in range(4):
        others = [j for j in range(4) if j != slot]
        rows = which == slot
        quats[rows, slot] = largest[rows]
        quats[np.ix_(rows, others)] = small[rows]
    for k in range(4):
        column[f"rot_{k}"] = quats[:, k]
    sh = arrays.get("sh")
    if sh is not None:
        rest = [f"f_rest_{i}" for i in range(len(sh.dtype.names))]
        if len(sh) != n or list(sh.dtype.names) != rest or len(rest) not in (9, 24, 45) \
                or any(sh.dtype[p] != np.dtype("u1") for p in rest):
            raise GaussianFileError(path, f"compressed PLY element 'sh' needs {n} rows of uchar "
                                          f"f_rest_0..N-1 with N in (9, 24, 45); got {len(sh)} rows of "
                                          f"{list(sh.dtype.names)}")
        for p in rest:
            b = sh[p].astype(np.float64)
            t = np.where(b == 0, 0.0, np.where(b == 255, 1.0, (b + 0.5) / 256.0))
            column[p] = (t - 0.5) * 8.0
    return column


def _check_quats(path, quats: np.ndarray) -> None:
    zero = np.linalg.norm(quats, axis=1) < 1e-12
    if np.any(zero):
        raise GaussianFileError(
            path,
            f"{int(zero.sum())} zero-length rotation quaternions "
            f"(first at Gaussian {np.flatnonzero(zero)[0]})",
        )


def _ply_columns(cloud: GaussianCloud) -> list[tuple[str, np.ndarray]]:
    k1 = cloud.sh.shape[1] - 1
    cols = [("x", cloud.means[:, 0]), ("y", cloud.means[:, 1]), ("z", cloud.means[:, 2])]
    cols += [(n, np.zeros(len(cloud), np.float32)) for n in ("nx", "ny", "nz")]
    cols += [(f"f_dc_{c}", cloud.sh[:, 0, c]) for c in range(3)]
    cols += [(f"f_rest_{c * k1 + j}", cloud.sh[:, 1 + j, c]) for c in range(3) for j in range(k1)]
    cols += [("opacity", cloud.logit_opacities)]
    cols += [(f"scale_{i}", cloud.log_scales[:, i]) for i in range(3)]
    cols += [(f"rot_{i}", cloud.quats[:, i]) for i in range(4)]
    return cols


def write_ply(cloud: GaussianCloud, path, *, ascii: bool = False) -> None:
    """Write an INRIA 3DGS .ply (float32; binary little endian, or ASCII with round-trip precision)."""
    cols = _ply_columns(cloud)
    fmt = "ascii" if ascii else "binary_little_endian"
    header = ["ply", f"format {fmt} 1.0", f"element vertex {len(cloud)}"]
    header += [f"property float {name}" for name, _ in cols] + ["end_header"]
    table = np.stack([np.asarray(c, dtype=np.float32) for _, c in cols], axis=1)
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        if ascii:
            if len(table):
                np.savetxt(f, table.astype(np.float64), fmt="%.9g")
        else:
            f.write(np.ascontiguousarray(table, dtype="<f4").tobytes())


# ----- .splat -----------------------------------------------------------------------------------------
_SPLAT_DTYPE = np.dtype([("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p, 1e-6, 1 - 1e-6)
    return np.log(p / (1 - p))


def _read_splat(path: Path, max_gaussians: int = MAX_GAUSSIANS) -> GaussianCloud:
    size = path.stat().st_size
    if size % 32:
        raise GaussianFileError(path, f"size {size} is not a multiple of 32 bytes (truncated .splat?)")
    _check_count(path, size // 32, max_gaussians)
    data = path.read_bytes()
    arr = np.frombuffer(data, dtype=_SPLAT_DTYPE)
    _check_finite(path, "position", arr["pos"])
    _check_finite(path, "scale", arr["scale"])
    if np.any(arr["scale"] <= 0):
        raise GaussianFileError(
            path, f"{int(np.sum(np.any(arr['scale'] <= 0, axis=1)))} Gaussians have scale <= 0"
        )
    quats = (arr["rot"].astype(np.float64) - 128.0) / 128.0
    _check_quats(path, quats)
    log_scales = np.log(arr["scale"].astype(np.float64))
    _check_log_scales(path, log_scales)
    rgba = arr["rgba"].astype(np.float64) / 255.0
    sh = ((rgba[:, :3] - 0.5) / SH_C0)[:, None, :]
    return GaussianCloud(
        arr["pos"],
        quats / np.linalg.norm(quats, axis=1, keepdims=True),
        log_scales,
        _logit(rgba[:, 3]),
        sh,
    )


def write_splat(cloud: GaussianCloud, path) -> None:
    """Write a 32-byte-per-Gaussian .splat (DC colour only; view-dependent SH is dropped). Bytes are
    rounded (antimatter15's converter truncates) and the order is kept (it sorts by size * opacity)."""
    out = np.zeros(len(cloud), dtype=_SPLAT_DTYPE)
    out["pos"] = cloud.means
    out["scale"] = cloud.scales
    rgb = np.clip(np.rint(cloud.base_colours * 255.0), 0, 255)
    alpha = np.clip(np.rint(cloud.opacities * 255.0), 0, 255)
    out["rgba"] = np.c_[rgb, alpha].astype(np.uint8)
    q = cloud.quats / np.linalg.norm(cloud.quats, axis=1, keepdims=True)
    out["rot"] = np.clip(np.rint(q * 128.0 + 128.0), 0, 255).astype(np.uint8)
    Path(path).write_bytes(out.tobytes())


# ----- .spz (Niantic) --------------------------------------------------------------------------------
SPZ_MAGIC = 0x5053474E  # "NGSP"
_SPZ_COLOUR_SCALE = 0.15
_SPZ_SH_DIM = {0: 0, 1: 3, 2: 8, 3: 15}
_SQRT1_2 = np.float32(np.sqrt(0.5))


def _flip_yz(cloud: GaussianCloud) -> GaussianCloud:
    """Convert between .spz's RUB axes and INRIA .ply's RDF axes (its own inverse): y and z negated,
    quaternion (w, x, -y, -z), SH coefficients of functions odd in (y, z) negated."""
    signs = np.concatenate(
        [np.diag(m) for m in sh_rotation_matrices(np.diag([1.0, -1.0, -1.0]), cloud.sh_degree)]
    )
    return GaussianCloud(
        cloud.means * np.array([1, -1, -1], np.float32),
        cloud.quats * np.array([1, 1, -1, -1], np.float32),
        cloud.log_scales,
        cloud.logit_opacities,
        cloud.sh * np.rint(signs).astype(np.float32)[None, :, None],
    )


def _gunzip_capped(path, raw: bytes, n_bytes: int) -> tuple[bytes, str]:
    """Inflate at most `n_bytes` of a gzip stream -> (data, "end" | "more" | "truncated"): "end" when the
    stream ends there (CRC checked), "more" when it holds more data (or bytes after it). Never inflates
    more than `n_bytes` + 1, whatever the stream claims (a gzip bomb costs nothing)."""
    d = zlib.decompressobj(wbits=16 + zlib.MAX_WBITS)  # gzip container
    try:
        out = d.decompress(raw, n_bytes)
        if d.unconsumed_tail and d.decompress(d.unconsumed_tail, 1):
            return out, "more"
    except zlib.error as exc:
        raise GaussianFileError(
            path, f"not a valid gzip stream ({exc}); .spz files are gzip-compressed"
        ) from None
    if not d.eof:
        return out, "truncated"
    return out, ("more" if d.unused_data else "end")


def _read_spz(path: Path, max_gaussians: int = MAX_GAUSSIANS) -> GaussianCloud:
    raw = path.read_bytes()
    if raw[:4] == b"NGSP":
        raise GaussianFileError(
            path,
            "uncompressed NGSP container (.spz version 4+) is not supported; save it as .spz version 2 or 3",
        )
    header, _ = _gunzip_capped(path, raw, 16)
    if len(header) < 16:
        raise GaussianFileError(path, f"truncated: {len(header)} bytes, the .spz header needs 16")
    magic, version, n, degree, frac_bits, flags, _ = struct.unpack("<IIIBBBB", header)
    if magic != SPZ_MAGIC:
        raise GaussianFileError(path, f"bad magic 0x{magic:08x} (expected 0x{SPZ_MAGIC:08x} 'NGSP')")
    if version not in (2, 3):
        raise GaussianFileError(path, f"unsupported .spz version {version} (supported: 2, 3)")
    if degree not in _SPZ_SH_DIM:
        raise GaussianFileError(path, f"SH degree {degree} out of range 0..3")
    if frac_bits > 24:
        raise GaussianFileError(path, f"{frac_bits} fractional bits for 24-bit positions (at most 24)")
    _check_count(path, n, max_gaussians)  # before inflating anything past the header
    if flags & 2:
        raise GaussianFileError(
            path,
            "holds .spz extension records (flag 0x2), which this reader does not parse; re-save without them",
        )
    if flags & 1:
        warnings.warn(
            f"{path}: antialiased .spz flag is set; rendered without antialiasing compensation", stacklevel=3
        )
    sh_dim = _SPZ_SH_DIM[degree]
    rot_bytes = 3 if version == 2 else 4
    sizes = [9 * n, n, 3 * n, 3 * n, rot_bytes * n, sh_dim * 3 * n]
    need = 16 + sum(sizes)
    data, state = _gunzip_capped(path, raw, need)
    if len(data) < need or state == "truncated":
        raise GaussianFileError(
            path, f"truncated: {n} points of SH degree {degree} need {need} bytes, got {len(data)}"
            + (" and the gzip stream ends early" if len(data) == need else "")
        )
    if state == "more":
        raise GaussianFileError(
            path, f"has trailing bytes: {n} points of SH degree {degree} need {need} bytes, the stream holds "
            "more (wrong point count in the header?)"
        )
    buf = np.frombuffer(data, dtype=np.uint8, offset=16)
    cuts = np.cumsum([0] + sizes)
    pos_b, alpha_b, col_b, scale_b, rot_b, sh_b = (buf[cuts[i] : cuts[i + 1]] for i in range(6))
    p = pos_b.reshape(n * 3, 3).astype(np.int32)
    fixed = p[:, 0] | (p[:, 1] << 8) | (p[:, 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    means = (fixed.astype(np.float64) / (1 << frac_bits)).reshape(n, 3)
    opac = _logit(alpha_b.astype(np.float64) / 255.0)
    dc = (col_b.reshape(n, 3).astype(np.float64) / 255.0 - 0.5) / _SPZ_COLOUR_SCALE
    log_scales = scale_b.reshape(n, 3).astype(np.float64) / 16.0 - 10.0
    if version == 2:
        xyz = rot_b.reshape(n, 3).astype(np.float64) / 127.5 - 1.0
        w = np.sqrt(np.maximum(0.0, 1.0 - np.sum(xyz * xyz, axis=1)))
        quats = np.c_[w, xyz]
    else:
        comp = rot_b.reshape(n, 4).astype(np.uint32)
        comp = comp[:, 0] | (comp[:, 1] << 8) | (comp[:, 2] << 16) | (comp[:, 3] << 24)
        largest = comp >> 30
        q = np.zeros((n, 4))  # xyzw
        mask = np.uint32(511)
        for i in (3, 2, 1, 0):
            sel = largest != i
            mag = (comp & mask).astype(np.float64)
            neg = (comp >> 9) & 1
            val = _SQRT1_2 * mag / 511.0
            q[sel, i] = np.where(neg[sel] == 1, -val[sel], val[sel])
            comp = np.where(sel, comp >> 10, comp)
        q[np.arange(n), largest] = np.sqrt(np.maximum(0.0, 1.0 - np.sum(q * q, axis=1)))
        quats = np.c_[q[:, 3], q[:, :3]]
    sh = np.zeros((n, sh_dim + 1, 3))
    sh[:, 0] = dc
    if sh_dim:
        sh[:, 1:] = (sh_b.reshape(n, sh_dim, 3).astype(np.float64) - 128.0) / 128.0
    return _flip_yz(GaussianCloud(means, quats, log_scales, opac, sh))


def _quantise_sh(x: np.ndarray, bits: int) -> np.ndarray:
    bucket = 1 << (8 - bits)
    q = np.rint(x * 128.0).astype(np.int64) + 128
    q = (q + bucket // 2) // bucket * bucket
    return np.clip(q, 0, 255).astype(np.uint8)


def write_spz(
    cloud: GaussianCloud, path, *, version: int = 3, fractional_bits: int = 12, antialiased: bool = False
) -> None:
    """Write a Niantic .spz (gzip; 24-bit fixed-point positions, 8-bit alpha/colour/log-scale, rotations as
    xyz bytes (v2) or smallest-three 32-bit (v3), SH 5 bits for degree 1 and 4 bits above)."""
    if version not in (2, 3):
        raise ValueError(f"write_spz: version must be 2 or 3, got {version}")
    cloud = _flip_yz(cloud)  # .spz stores RUB axes
    n = len(cloud)
    fixed = np.rint(cloud.means.astype(np.float64) * (1 << fractional_bits)).astype(np.int64)
    if np.any(np.abs(fixed) >= (1 << 23)):
        raise ValueError(
            f"write_spz: positions exceed the 24-bit range (|x| < {2 ** (23 - fractional_bits)} m "
            f"with fractional_bits={fractional_bits}); lower fractional_bits"
        )
    fixed = fixed.reshape(-1) & 0xFFFFFF
    pos = np.stack([fixed & 0xFF, (fixed >> 8) & 0xFF, (fixed >> 16) & 0xFF], 1).astype(np.uint8)
    u8 = lambda x: np.clip(np.rint(x), 0, 255).astype(np.uint8)  # noqa: E731
    alpha = u8(cloud.opacities.astype(np.float64) * 255.0)
    colour = u8(cloud.sh[:, 0].astype(np.float64) * (_SPZ_COLOUR_SCALE * 255.0) + 0.5 * 255.0)
    scale = u8((cloud.log_scales.astype(np.float64) + 10.0) * 16.0)
    q = cloud.quats.astype(np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    xyzw = np.c_[q[:, 1:], q[:, 0]]
    if version == 2:
        xyzw = xyzw * np.where(xyzw[:, 3:] < 0, -127.5, 127.5) + 127.5
        rot = u8(xyzw[:, :3])
    else:
        largest = np.argmax(np.abs(xyzw), axis=1)
        negate = xyzw[np.arange(n), largest] < 0
        comp = largest.astype(np.uint32)
        for i in range(4):
            sel = largest != i
            negbit = ((xyzw[:, i] < 0) ^ negate).astype(np.uint32)
            mag = (511.0 * (np.abs(xyzw[:, i]) / np.sqrt(0.5)) + 0.5).astype(np.uint32)
            comp = np.where(sel, (comp << 10) | (negbit << 9) | mag, comp)
        rot = np.stack([(comp >> s) & 0xFF for s in (0, 8, 16, 24)], 1).astype(np.uint8)
    degree = cloud.sh_degree
    sh_rest = cloud.sh[:, 1:].reshape(n, -1).astype(np.float64)  # coefficient-major, rgb inner
    sh = np.zeros_like(sh_rest, dtype=np.uint8)
    if sh_rest.shape[1]:
        sh[:, :9] = _quantise_sh(sh_rest[:, :9], 5)
        sh[:, 9:] = _quantise_sh(sh_rest[:, 9:], 4)
    header = struct.pack(
        "<IIIBBBB", SPZ_MAGIC, version, n, degree, fractional_bits, 1 if antialiased else 0, 0
    )
    body = b"".join(a.tobytes() for a in (pos, alpha, colour, scale, rot, sh))
    Path(path).write_bytes(gzip.compress(header + body, compresslevel=6))


# ----- dispatch ---------------------------------------------------------------------------------------
_READERS = {".ply": _read_ply, ".splat": _read_splat, ".spz": _read_spz}


def load_gaussians(path, *, max_gaussians: int = MAX_GAUSSIANS) -> GaussianCloud:
    """Read a .ply, .splat or .spz file into a GaussianCloud (validated; GaussianFileError on bad input).

    A file declaring more than `max_gaussians` Gaussians is refused before its data is read/inflated."""
    path = Path(path)
    reader = _READERS.get(path.suffix.lower())
    if reader is None:
        raise GaussianFileError(
            path, f"unknown extension {path.suffix!r}; expected one of {sorted(_READERS)}"
        )
    if not path.is_file():
        raise GaussianFileError(path, "file not found")
    try:
        return reader(path, max_gaussians=int(max_gaussians))
    except GaussianFileError:
        raise
    except ValueError as exc:  # e.g. GaussianCloud shape validation
        raise GaussianFileError(path, str(exc)) from None


def save_gaussians(cloud: GaussianCloud, path, *, ascii: bool = False, spz_version: int = 3) -> None:
    """Write a GaussianCloud by extension (.ply binary unless ascii=True; .splat; .spz)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".ply":
        write_ply(cloud, path, ascii=ascii)
    elif suffix == ".splat":
        write_splat(cloud, path)
    elif suffix == ".spz":
        write_spz(cloud, path, version=spz_version)
    else:
        raise ValueError(f"save_gaussians: unknown extension {suffix!r} for {path}; use .ply, .splat or .spz")
