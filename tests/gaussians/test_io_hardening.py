"""Gaussian file hardening (issue 14): .spz bombs, huge declared counts, out-of-range values, image sizes."""

from __future__ import annotations

import gzip
import struct
import time
import tracemalloc
import zlib

import pytest

from twinbench.cli import main as cli_main
from twinbench.errors import InputError
from twinbench.gaussians.io import SPZ_MAGIC, GaussianFileError, load_gaussians, save_gaussians, write_ply


def _gzip_stream(header: bytes, zeros: int) -> bytes:
    """gzip(header + `zeros` zero bytes), built incrementally."""
    c = zlib.compressobj(9, zlib.DEFLATED, 16 + zlib.MAX_WBITS)
    parts, chunk = [c.compress(header)], bytes(1 << 20)
    for _ in range(zeros // len(chunk)):
        parts.append(c.compress(chunk))
    parts.append(c.compress(bytes(zeros % len(chunk))) + c.flush())
    return b"".join(parts)


def test_spz_bomb_is_never_inflated(tmp_path):
    # 1000 points of SH degree 0 need 16 + 19 * 1000 bytes; the stream inflates to 256 MiB (a 250 kB file)
    path = tmp_path / "bomb.spz"
    path.write_bytes(_gzip_stream(struct.pack("<IIIBBBB", SPZ_MAGIC, 2, 1000, 0, 12, 0, 0), 2**28))
    assert path.stat().st_size < 2**20
    t0 = time.monotonic()
    tracemalloc.start()
    try:
        with pytest.raises(GaussianFileError, match="trailing bytes"):
            load_gaussians(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 4 * 2**20  # the file + 19 kB of data, never the 256 MiB
    assert time.monotonic() - t0 < 2


def test_spz_huge_declared_count_is_refused_before_inflating(tmp_path, make_cloud):
    path = tmp_path / "huge.spz"
    path.write_bytes(gzip.compress(struct.pack("<IIIBBBB", SPZ_MAGIC, 3, 2**32 - 1, 3, 12, 0, 0)))
    with pytest.raises(GaussianFileError, match="declares 4294967295 Gaussians, over the limit"):
        load_gaussians(path)
    small = tmp_path / "small.spz"
    save_gaussians(make_cloud(50, seed=1), small)
    with pytest.raises(GaussianFileError, match="max_gaussians"):
        load_gaussians(small, max_gaussians=10)
    assert len(load_gaussians(small)) == 50


def test_spz_truncated_gzip_stream_is_refused(tmp_path, make_cloud):
    good = tmp_path / "good.spz"
    save_gaussians(make_cloud(200, seed=3), good)
    cut = tmp_path / "cut.spz"
    cut.write_bytes(good.read_bytes()[:-6])  # the CRC/size trailer is gone
    with pytest.raises(GaussianFileError, match="truncated"):
        load_gaussians(cut)


@pytest.mark.parametrize("value", [1e30, -1e30, 25.0, -40.0])
def test_out_of_range_log_scale_is_refused(tmp_path, make_cloud, value):
    cloud = make_cloud(20, seed=2)
    cloud.log_scales[7, 1] = value
    path = tmp_path / "s.ply"
    write_ply(cloud, path)
    with pytest.raises(GaussianFileError, match=r"log-scale outside \[-30, 20\] \(first at Gaussian 7"):
        load_gaussians(path)


def test_splat_with_a_huge_linear_scale_is_refused(tmp_path, make_cloud):
    path = tmp_path / "s.splat"
    save_gaussians(make_cloud(10, seed=4), path)
    data = bytearray(path.read_bytes())
    data[32 * 3 + 12:32 * 3 + 16] = struct.pack("<f", 1e30)  # Gaussian 3, scale x
    path.write_bytes(bytes(data))
    with pytest.raises(GaussianFileError, match="first at Gaussian 3"):
        load_gaussians(path)


def test_ply_header_with_a_huge_count_is_refused(tmp_path, make_cloud):
    path = tmp_path / "h.ply"
    write_ply(make_cloud(5, seed=5), path)
    data = path.read_bytes().replace(b"element vertex 5\n", b"element vertex 999999999999\n")
    path.write_bytes(data)
    with pytest.raises(GaussianFileError, match="over the limit"):
        load_gaussians(path)
    path.write_bytes(data.replace(b"999999999999", b"9999999"))
    with pytest.raises(GaussianFileError, match="declares 9999999 rows"):
        load_gaussians(path, max_gaussians=10**8)
    assert issubclass(GaussianFileError, InputError)


BAD_OPTIONS = [
    (["--width", "200000"], "--width 200000: must be between 1 and 8192"),
    (["--height", "0"], "--height 0"),
    (["--fov-deg", "180"], "--fov-deg"),
    (["--percentile", "0"], "--percentile"),
    (["--view-dir", "0", "0", "0"], "--view-dir"),
]


@pytest.mark.parametrize("args, needle", BAD_OPTIONS)
def test_render_ply_validates_options_before_loading_or_allocating(tmp_path, capsys, make_cloud, args,
                                                                   needle):
    src = tmp_path / "c.ply"
    write_ply(make_cloud(30, seed=6), src)
    t0 = time.monotonic()
    tracemalloc.start()
    try:
        code = cli_main(["render-ply", str(src), "--out", str(tmp_path / "x.png"), *args])
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and needle in err[0], err
    assert peak < 100 * 2**20 and time.monotonic() - t0 < 10  # (imports included; was 6 GB)
    assert not (tmp_path / "x.png").exists()


def test_render_ply_of_a_log_scale_1e30_file_is_exit_2_not_a_black_image(tmp_path, capsys, make_cloud):
    cloud = make_cloud(30, seed=7)
    cloud.log_scales[:] = 1e30
    src = tmp_path / "bad.ply"
    write_ply(cloud, src)
    assert cli_main(["render-ply", str(src), "--out", str(tmp_path / "x.png"), "--width", "32",
                     "--height", "32"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.ply" in err[0] and "log-scale" in err[0]
    assert not (tmp_path / "x.png").exists()
