"""File formats: exact .ply round trips, quantised .splat/.spz round trips, clear errors on bad files."""

from __future__ import annotations

import gzip
import struct

import numpy as np
import pytest

from twinbench.gaussians.cloud import GaussianCloud
from twinbench.gaussians.io import GaussianFileError, load_gaussians, save_gaussians


def _unit(q):
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    return q * np.sign(q[:, :1] + 1e-30)


def _rotation_error(a, b):
    """1 - |<qa, qb>| (0 for the same rotation; ~ angle^2 / 8)."""
    return np.abs(1 - np.abs(np.sum(_unit(a) * _unit(b), axis=1))).max()


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("ascii", [False, True])
def test_ply_round_trip_is_exact(tmp_path, make_cloud, degree, ascii):
    cloud = make_cloud(64, degree=degree, seed=degree)
    path = tmp_path / "c.ply"
    save_gaussians(cloud, path, ascii=ascii)
    assert path.read_bytes().startswith(b"ply\nformat " + (b"ascii" if ascii else b"binary_little_endian"))
    back = load_gaussians(path)
    for name in ("means", "quats", "log_scales", "logit_opacities", "sh"):
        np.testing.assert_array_equal(getattr(back, name), getattr(cloud, name), err_msg=name)


def test_ply_rest_layout_is_channel_major(tmp_path):
    # INRIA: f_rest index = channel * (K - 1) + coefficient
    sh = np.zeros((1, 4, 3), np.float32)
    sh[0, 2, 1] = 7.0  # coefficient 2 (rest index 1), green (channel 1) -> f_rest_{1*3 + 1} = f_rest_4
    cloud = GaussianCloud([[0, 0, 0]], [[1, 0, 0, 0]], [[0, 0, 0]], [0.0], sh)
    path = tmp_path / "c.ply"
    save_gaussians(cloud, path, ascii=True)
    text = path.read_text()
    header, body = text.split("end_header\n")
    names = [ln.split()[-1] for ln in header.splitlines() if ln.startswith("property")]
    values = body.split()
    assert float(values[names.index("f_rest_4")]) == 7.0
    assert sum(float(v) for v in values[names.index("f_rest_0") : names.index("f_rest_8") + 1]) == 7.0


def test_ply_with_big_endian_and_extra_properties(tmp_path, make_cloud):
    cloud = make_cloud(10, degree=1, seed=3)
    k1 = 3
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(9)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3", "extra_thing"]
    cols = [cloud.means[:, i] for i in range(3)] + [cloud.sh[:, 0, c] for c in range(3)]
    cols += [cloud.sh[:, 1 + j, c] for c in range(3) for j in range(k1)]
    cols += [cloud.logit_opacities] + [cloud.log_scales[:, i] for i in range(3)]
    cols += [cloud.quats[:, i] for i in range(4)] + [np.ones(10, np.float32)]
    header = "ply\nformat binary_big_endian 1.0\nelement vertex 10\n"
    header += "".join(f"property float {n}\n" for n in names) + "end_header\n"
    path = tmp_path / "be.ply"
    path.write_bytes(header.encode() + np.stack(cols, 1).astype(">f4").tobytes())
    with pytest.warns(UserWarning, match="extra_thing"):
        back = load_gaussians(path)
    for name in ("means", "quats", "log_scales", "logit_opacities", "sh"):
        np.testing.assert_array_equal(getattr(back, name), getattr(cloud, name), err_msg=name)


def test_splat_round_trip_within_quantisation(tmp_path, make_cloud):
    cloud = make_cloud(200, degree=2, seed=5)
    cloud.sh[:, 0] = np.random.default_rng(0).uniform(-1.5, 1.5, size=(200, 3))  # colours inside [0, 1]
    path = tmp_path / "c.splat"
    save_gaussians(cloud, path)
    assert path.stat().st_size == 32 * 200
    back = load_gaussians(path)
    assert back.sh_degree == 0
    np.testing.assert_array_equal(back.means, cloud.means)
    np.testing.assert_allclose(back.log_scales, cloud.log_scales, atol=1e-6)
    np.testing.assert_allclose(back.base_colours, cloud.base_colours, atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(back.opacities, cloud.opacities, atol=0.5 / 255 + 1e-6)
    assert _rotation_error(back.quats, cloud.quats) < 2e-4  # 1/256 per component


@pytest.mark.parametrize("version", [2, 3])
def test_spz_round_trip_within_quantisation(tmp_path, make_cloud, version):
    cloud = make_cloud(300, degree=3, seed=6, spread=2.0)
    path = tmp_path / "c.spz"
    save_gaussians(cloud, path, spz_version=version)
    raw = gzip.decompress(path.read_bytes())
    magic, ver, n, deg, frac, flags, _ = struct.unpack("<IIIBBBB", raw[:16])
    assert (magic, ver, n, deg, frac) == (0x5053474E, version, 300, 3, 12)
    assert raw[:4] == b"NGSP"
    back = load_gaussians(path)
    np.testing.assert_allclose(back.means, cloud.means, atol=0.5 / 4096 + 1e-6)
    np.testing.assert_allclose(back.log_scales, cloud.log_scales, atol=0.5 / 16 + 1e-6)
    np.testing.assert_allclose(back.opacities, cloud.opacities, atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(back.sh[:, 0], cloud.sh[:, 0], atol=0.5 / 255 / 0.15 + 1e-6)
    # degree-1 SH: 5 bits (bucket 8/128), higher: 4 bits (bucket 16/128), plus rounding to 1/128
    np.testing.assert_allclose(back.sh[:, 1:4], cloud.sh[:, 1:4], atol=4.5 / 128 + 1e-6)
    np.testing.assert_allclose(back.sh[:, 4:], cloud.sh[:, 4:], atol=8.5 / 128 + 1e-6)
    # v2 stores xyz only and rebuilds w, which is ill-conditioned for w ~ 0 (the reason v3 exists)
    assert _rotation_error(back.quats, cloud.quats) < (2e-5 if version == 3 else 5e-3)


def test_spz_known_bytes_and_rub_axes(tmp_path):
    """Hand-encoded one-point v2 file (degree 1). .spz stores RUB axes; we read INRIA's RDF: y, z negated."""
    pos = b"".join((int(round(v * 4096)) & 0xFFFFFF).to_bytes(3, "little") for v in (1.0, -0.5, 0.25))
    alpha, colour = bytes([255]), bytes([int(round(0.5 * 255))] * 3)
    scale = bytes([int((np.log(0.01) + 10) * 16 + 0.5)] * 3)
    rot = bytes([191, 191, 191])  # xyz of the xyzw quaternion (0.5, 0.5, 0.5, 0.5)
    sh = bytes([192] * 9)  # every degree-1 coefficient = 0.5, coefficient-major, rgb inner
    body = struct.pack("<IIIBBBB", 0x5053474E, 2, 1, 1, 12, 0, 0) + pos + alpha + colour + scale + rot + sh
    path = tmp_path / "one.spz"
    path.write_bytes(gzip.compress(body))
    c = load_gaussians(path)
    np.testing.assert_allclose(c.means[0], [1.0, 0.5, -0.25])
    np.testing.assert_allclose(c.scales[0], 0.01, rtol=0.04)
    x = 191 / 127.5 - 1
    np.testing.assert_allclose(c.quats[0], [np.sqrt(1 - 3 * x * x), x, -x, -x], atol=1e-6)
    assert c.opacities[0] > 0.999
    np.testing.assert_allclose(c.sh[0, 0], (128 / 255 - 0.5) / 0.15, atol=1e-6)  # byte 128
    # basis functions -C1 y, C1 z, -C1 x: the first two change sign under (x, y, z) -> (x, -y, -z)
    np.testing.assert_allclose(c.sh[0, 1:], [[-0.5] * 3, [-0.5] * 3, [0.5] * 3])


def test_spz_extension_flag_and_v4_container_are_rejected(tmp_path):
    path = tmp_path / "ext.spz"
    path.write_bytes(gzip.compress(struct.pack("<IIIBBBB", 0x5053474E, 3, 0, 0, 12, 2, 0)))
    with pytest.raises(GaussianFileError, match="extension"):
        load_gaussians(path)
    path.write_bytes(b"NGSP" + bytes(28))
    with pytest.raises(GaussianFileError, match="version 4"):
        load_gaussians(path)


def _good_ply(tmp_path, make_cloud, ascii=False):
    path = tmp_path / ("a.ply" if ascii else "b.ply")
    save_gaussians(make_cloud(20, degree=1), path, ascii=ascii)
    return path


def test_truncated_files_raise_clear_errors(tmp_path, make_cloud):
    ply = _good_ply(tmp_path, make_cloud)
    ply.write_bytes(ply.read_bytes()[:-10])
    with pytest.raises(GaussianFileError, match=r"b\.ply: truncated"):
        load_gaussians(ply)
    ascii_ply = _good_ply(tmp_path, make_cloud, ascii=True)
    lines = ascii_ply.read_text().splitlines()
    ascii_ply.write_text("\n".join(lines[:-3]) + "\n")
    with pytest.raises(GaussianFileError, match="20 vertices"):
        load_gaussians(ascii_ply)
    splat = tmp_path / "c.splat"
    save_gaussians(make_cloud(4), splat)
    splat.write_bytes(splat.read_bytes()[:-5])
    with pytest.raises(GaussianFileError, match="multiple of 32"):
        load_gaussians(splat)
    spz = tmp_path / "c.spz"
    save_gaussians(make_cloud(4, degree=1), spz)
    spz.write_bytes(gzip.compress(gzip.decompress(spz.read_bytes())[:-7]))
    with pytest.raises(GaussianFileError, match="truncated"):
        load_gaussians(spz)
    spz.write_bytes(b"not gzip at all")
    with pytest.raises(GaussianFileError, match="gzip"):
        load_gaussians(spz)
    spz.write_bytes(gzip.compress(struct.pack("<IIIBBBB", 0x12345678, 2, 0, 0, 12, 0, 0)))
    with pytest.raises(GaussianFileError, match="magic"):
        load_gaussians(spz)


def test_ply_missing_property_nan_and_wrong_count(tmp_path, make_cloud):
    path = _good_ply(tmp_path, make_cloud, ascii=True)
    text = path.read_text()
    # drop the opacity column entirely
    header, body = text.split("end_header\n")
    names = [ln.split()[-1] for ln in header.splitlines() if ln.startswith("property")]
    i = names.index("opacity")
    new_header = "\n".join(ln for ln in header.splitlines() if not ln.endswith(" opacity")) + "\nend_header\n"
    rows = [" ".join(v for j, v in enumerate(r.split()) if j != i) for r in body.splitlines()]
    missing = tmp_path / "missing.ply"
    missing.write_text(new_header + "\n".join(rows) + "\n")
    with pytest.raises(GaussianFileError, match=r"missing.ply: missing vertex properties \['opacity'\]"):
        load_gaussians(missing)
    # NaN in a position
    bad_rows = body.splitlines()
    bad_rows[3] = "nan " + " ".join(bad_rows[3].split()[1:])
    nan_file = tmp_path / "nan.ply"
    nan_file.write_text(header + "end_header\n" + "\n".join(bad_rows) + "\n")
    with pytest.raises(GaussianFileError, match="non-finite.*Gaussian 3"):
        load_gaussians(nan_file)
    # header says 25 vertices, binary body has 20
    cloud = make_cloud(20, degree=1)
    binary = tmp_path / "count.ply"
    save_gaussians(cloud, binary)
    binary.write_bytes(binary.read_bytes().replace(b"element vertex 20", b"element vertex 25"))
    with pytest.raises(GaussianFileError, match="25 vertices"):
        load_gaussians(binary)
    binary.write_bytes(binary.read_bytes().replace(b"element vertex 25", b"element vertex 15"))
    with pytest.raises(GaussianFileError, match="unexpected bytes"):
        load_gaussians(binary)
    # a wrong number of f_rest properties
    odd = tmp_path / "odd.ply"
    odd.write_text(text.replace("property float f_rest_8\n", ""))
    with pytest.raises(GaussianFileError, match="f_rest"):
        load_gaussians(odd)


def test_unknown_extension_and_missing_file(tmp_path, make_cloud):
    with pytest.raises(GaussianFileError, match="extension"):
        load_gaussians(tmp_path / "x.obj")
    with pytest.raises(GaussianFileError, match="not found"):
        load_gaussians(tmp_path / "x.ply")
    with pytest.raises(ValueError, match="extension"):
        save_gaussians(make_cloud(3), tmp_path / "x.obj")
    assert issubclass(GaussianFileError, ValueError)


# ----- SuperSplat's compressed .ply: files built here bit by bit from the layout ------------------------
_BOUNDS = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z", "min_scale_x", "min_scale_y", "min_scale_z",
           "max_scale_x", "max_scale_y", "max_scale_z"]


def _compressed_ply(path, chunks: list[dict], words: np.ndarray, sh: np.ndarray | None = None,
                    n_chunks: int | None = None) -> None:
    """A SuperSplat compressed .ply: per chunk its float bounds, per Gaussian its four packed uint32
    (position, rotation, scale, colour) and optionally its uchar f_rest_* row."""
    names = list(chunks[0])
    lines = ["ply", "format binary_little_endian 1.0", f"element chunk {n_chunks or len(chunks)}"]
    lines += [f"property float {p}" for p in names]
    lines += [f"element vertex {len(words)}"]
    lines += [f"property uint packed_{p}" for p in ("position", "rotation", "scale", "color")]
    if sh is not None:
        lines += [f"element sh {len(sh)}"] + [f"property uchar f_rest_{i}" for i in range(sh.shape[1])]
    body = np.array([[c[p] for p in names] for c in chunks], "<f4").tobytes()
    body += np.asarray(words, "<u4").tobytes() + (b"" if sh is None else np.asarray(sh, "u1").tobytes())
    path.write_bytes(("\n".join(lines + ["end_header"]) + "\n").encode() + body)


def _pack(fields: list[tuple[int, int]]) -> int:
    """(value, bits) from the top bits down -> one uint32."""
    word, left = 0, 32
    for value, bits in fields:
        left -= bits
        word |= value << left
    return word


def test_compressed_ply_decodes_each_field_by_the_layout(tmp_path):

    chunk = dict(zip(_BOUNDS, [0.0, 0.0, -1.0, 2.047, 1.023, 1.047, -6.0, -5.0, -4.0, -4.0, -3.0, -2.0],
                     strict=True))
    s2 = np.sqrt(2.0)
    words = np.array([
        # position 1000/2047, 500/1023, 2047/2047 of the bounds; scale 0, 1023/1023, 0; rgba 255, 0, 128,
        # 204; rotation: the largest in slot 0 (w), the others at 511/1023
        [_pack([(1000, 11), (500, 10), (2047, 11)]), _pack([(0, 2), (511, 10), (511, 10), (511, 10)]),
         _pack([(0, 11), (1023, 10), (0, 11)]), _pack([(255, 8), (0, 8), (128, 8), (204, 8)])],
        # a quarter turn about z: w = (1023/1023 - 0.5) sqrt(2) = 1/sqrt(2) in the first small slot, z the
        # largest (slot 3)
        [_pack([(0, 11), (0, 10), (0, 11)]), _pack([(3, 2), (1023, 10), (511, 10), (511, 10)]),
         _pack([(2047, 11), (0, 10), (2047, 11)]), _pack([(0, 8), (255, 8), (0, 8), (0, 8)])],
    ], dtype=np.uint32)
    sh = np.zeros((2, 9), np.uint8)
    sh[0, :3] = [0, 255, 128]
    path = tmp_path / "compressed.ply"
    _compressed_ply(path, [chunk], words, sh)
    cloud = load_gaussians(path)
    np.testing.assert_allclose(cloud.means, [[1.0, 0.5, 1.047], [0.0, 0.0, -1.0]], atol=1e-6)
    np.testing.assert_allclose(cloud.log_scales, [[-6.0, -3.0, -4.0], [-4.0, -5.0, -2.0]], atol=1e-6)
    np.testing.assert_allclose(cloud.base_colours, [[1.0, 0.0, 128 / 255], [0.0, 1.0, 0.0]], atol=1e-6)
    np.testing.assert_allclose(cloud.opacities[0], 0.8, atol=1e-6)
    assert cloud.opacities[1] < 1e-5
    small = (511 / 1023 - 0.5) * s2
    big = np.sqrt(1 - 3 * small**2)
    np.testing.assert_allclose(cloud.quats[0], [big, small, small, small], atol=1e-6)
    np.testing.assert_allclose(cloud.quats[1], [1 / s2, small, small, np.sqrt(0.5 - 2 * small**2)], atol=1e-6)
    assert cloud.sh_degree == 1
    # f_rest_* channel-major as in an INRIA .ply: f_rest_0..2 are red's three degree-1 coefficients;
    # bytes 0 and 255 are -4 and 4, the others the middle of their 1/256 bin
    np.testing.assert_allclose(cloud.sh[0, 1:, 0], [-4.0, 4.0, (128.5 / 256 - 0.5) * 8], atol=1e-6)
    np.testing.assert_allclose(cloud.sh[0, 1:, 1:], -4.0 * np.ones((3, 2)), atol=1e-6)


def test_compressed_ply_uses_each_chunks_bounds_and_colour_range(tmp_path):
    chunks = []
    for k in range(2):  # 300 Gaussians: chunk 0 holds 256, chunk 1 the last 44
        c = dict(zip(_BOUNDS, [k, 0, 0, k + 2.047, 1.023, 2.047, -5, -5, -5, -3, -3, -3], strict=True))
        c.update(min_r=0.25 * k, min_g=0.0, min_b=0.0, max_r=0.25 * k + 0.5, max_g=1.0, max_b=1.0)
        chunks.append(c)
    idx = np.arange(300)
    words = np.zeros((300, 4), np.uint32)
    words[:, 0] = [_pack([(int(i), 11), (0, 10), (0, 11)]) for i in idx]
    words[:, 1] = _pack([(0, 2), (511, 10), (511, 10), (511, 10)])
    words[:, 3] = [_pack([(255, 8), (0, 8), (0, 8), (255, 8)]) for _ in idx]
    path = tmp_path / "two_chunks.ply"
    _compressed_ply(path, chunks, words)
    cloud = load_gaussians(path)
    k = idx // 256
    np.testing.assert_allclose(cloud.means[:, 0], k + idx / 1000, atol=1e-5)
    np.testing.assert_allclose(cloud.base_colours[:, 0], 0.25 * k + 0.5, atol=1e-6)  # red at its chunk's max
    assert cloud.sh_degree == 0 and len(cloud) == 300


def test_compressed_ply_errors_name_the_problem(tmp_path):
    chunk = dict(zip(_BOUNDS, [0.0] * 6 + [-5.0] * 6, strict=True))
    words = np.tile(np.uint32(_pack([(0, 2), (511, 10), (511, 10), (511, 10)])), (3, 4))
    path = tmp_path / "bad.ply"
    _compressed_ply(path, [chunk], words, n_chunks=2)
    with pytest.raises(GaussianFileError, match="truncated: element 'vertex' declares 3 rows"):
        load_gaussians(path)
    _compressed_ply(path, [chunk, chunk], words)
    with pytest.raises(GaussianFileError, match="2 chunks for 3 Gaussians; .* one chunk per 256"):
        load_gaussians(path)
    _compressed_ply(path, [chunk], words, sh=np.zeros((3, 5), np.uint8))
    with pytest.raises(GaussianFileError, match="element 'sh' needs 3 rows of uchar"):
        load_gaussians(path)
    path.write_bytes(path.read_bytes().replace(b"binary_little_endian", b"binary_big_endian"))
    with pytest.raises(GaussianFileError, match="compressed PLY .* is binary little endian"):
        load_gaussians(path)


def test_compressed_ply_from_splat_transform_matches_its_source():
    """A file written by PlayCanvas's own encoder (tests/data/supersplat/README.md) decodes to its source
    within the layout's steps: 11/10 bits of a chunk's extent, 8 bits of colour, 10-bit rotations, SH
    bytes."""
    from pathlib import Path

    from scipy.spatial import cKDTree

    data = Path(__file__).resolve().parents[1] / "data" / "supersplat"
    src, got = load_gaussians(data / "cloud.ply"), load_gaussians(data / "cloud.compressed.ply")
    assert len(got) == len(src) == 300 and got.sh_degree == src.sh_degree == 1
    dist, j = cKDTree(src.means).query(got.means)  # splat-transform writes them in Morton order
    assert sorted(j) == list(range(300))
    assert dist.max() < 2.0 / 1023  # chunk extents <= 2 m, 10 bits on y
    np.testing.assert_allclose(got.log_scales, src.log_scales[j], atol=4.0 / 1023)
    assert _rotation_error(got.quats, src.quats[j]) < 1e-5
    np.testing.assert_allclose(got.base_colours, src.base_colours[j], atol=1.0 / 255)
    np.testing.assert_allclose(got.opacities, src.opacities[j], atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(got.sh[:, 1:], src.sh[j, 1:], atol=4.0 / 256 + 1e-6)
