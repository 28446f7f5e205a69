"""The PhysTwin readers (restricted pickle and torch-archive loaders) under hostile files: deflate bombs,
far memo slots, shared-reference DAGs, deep nesting and damaged archives each end in a PhysTwinFormatError
naming the file, within seconds and a bounded peak memory (issue 25)."""

from __future__ import annotations

import pickle
import struct
import zipfile
import zlib

import numpy as np
import pytest
from bombs import GIB, peak_mb, write_zip, zeros_bomb

from twinbench.cli import main as cli
from twinbench.construct.phystwin import PhysTwinFormatError, load_pickle, load_torch_zip, save_torch_zip


def _archive_members(tmp_path, numel=None):
    """(data.pkl, byteorder) of a real archive holding one float32 tensor of 3 elements; `numel` rewrites
    the element count its storage declares."""
    save_torch_zip({"spring_Y": np.ones(3, np.float32)}, tmp_path / "plain.pth")
    with zipfile.ZipFile(tmp_path / "plain.pth") as zf:
        data = zf.read("plain/data.pkl")
    if numel is not None:
        count = b"cpuq\x04K\x03t"  # the storage's persistent id ends (..., 'cpu', 3): BININT1 3
        assert data.count(count) == 1
        data = data.replace(count, b"cpuq\x04J" + struct.pack("<i", numel) + b"t")
    return [("plain/data.pkl", data), ("plain/byteorder", b"little")]


def _try(call: str) -> str:
    return ("from twinbench.construct.phystwin import *\n"
            f"try:\n    {call}\n    print('loaded')\n"
            "except PhysTwinFormatError as e:\n    print('refused:', e)")


def test_a_deflate_bomb_record_is_never_inflated_whole(tmp_path):
    members = _archive_members(tmp_path) + [("plain/data/0", zeros_bomb(3 * GIB))]
    bomb = write_zip(tmp_path / "best_1.pth", members)
    peak, said = peak_mb(_try(f"print(load_torch_zip({str(bomb)!r})['spring_Y'].tolist())"))
    assert said == "loaded" and peak < 400, (said, peak)  # 3 elements read of 3 GiB; base ~150 MB


def test_a_tensor_declaring_gigabytes_is_refused_before_reading(tmp_path):
    members = _archive_members(tmp_path, numel=2**31 - 1) + [("plain/data/0", zeros_bomb(3 * GIB))]
    bomb = write_zip(tmp_path / "best_1.pth", members)
    peak, said = peak_mb(_try(f"load_torch_zip({str(bomb)!r})"))
    assert said.startswith("refused:") and "best_1.pth" in said and "MiB" in said and peak < 400, (said, peak)


def test_a_data_pkl_bomb_is_refused(tmp_path):
    bomb = write_zip(tmp_path / "best_1.pth", [("plain/data.pkl", zeros_bomb(GIB))])
    peak, said = peak_mb(_try(f"load_torch_zip({str(bomb)!r})"))
    assert said.startswith("refused:") and "data.pkl inflates" in said and peak < 400, (said, peak)


def test_a_far_memo_slot_is_refused_before_the_memo_grows(tmp_path):
    path = tmp_path / "optimal_params.pkl"
    path.write_bytes(b"\x80\x02}r" + struct.pack("<I", 508_269_683) + b".")  # 1.4 kB in the issue: 12 B
    peak, said = peak_mb(_try(f"load_pickle({str(path)!r})"))
    assert said.startswith("refused:") and "memo slot 508269683" in said and peak < 400, (said, peak)


def test_a_shared_reference_dag_of_2_to_the_60_leaves_is_refused_quickly(tmp_path):
    value = [np.zeros(3)]
    for _ in range(60):
        value = [value, value]
    path = tmp_path / "final_data.pkl"
    path.write_bytes(pickle.dumps({"object_points": value}, protocol=2))
    assert path.stat().st_size < 2000
    with pytest.raises(PhysTwinFormatError, match=r"final_data\.pkl.*expands to more than"):
        load_pickle(path)


def test_a_shared_array_counts_its_bytes_at_each_reference(tmp_path):
    big = np.zeros(1 << 20)  # 8 MiB, referenced 128 times: 1 GiB once expanded
    path = tmp_path / "final_data.pkl"
    path.write_bytes(pickle.dumps({"object_points": [big] * 128}, protocol=2))
    with pytest.raises(PhysTwinFormatError, match="MiB of arrays"):
        load_pickle(path)


def test_100000_nested_lists_are_refused_without_recursion_error(tmp_path):
    n = 100_000
    path = tmp_path / "final_data.pkl"
    path.write_bytes(b"\x80\x02" + b"]" * n + b"a" * (n - 1) + b".")
    with pytest.raises(PhysTwinFormatError, match=r"final_data\.pkl.*nested more than 64 deep"):
        load_pickle(path)


def test_a_list_that_contains_itself_is_refused(tmp_path):
    loop: list = []
    loop.append(loop)
    path = tmp_path / "final_data.pkl"
    path.write_bytes(pickle.dumps(loop, protocol=2))
    with pytest.raises(PhysTwinFormatError, match="contains itself"):
        load_pickle(path)


def test_a_damaged_archive_names_the_file(tmp_path):
    save_torch_zip({"spring_Y": np.arange(1000, dtype=np.float32)}, tmp_path / "ok.pth")
    with zipfile.ZipFile(tmp_path / "ok.pth") as zf:
        members = [(n, zf.read(n)) for n in zf.namelist()]
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    record = dict(members)["ok/data/0"]
    stream = bytearray(c.compress(record) + c.flush())
    stream[len(stream) // 2] ^= 0xFF  # damaged compressed data
    members = [(n, (bytes(stream), zlib.crc32(record), len(record)) if n == "ok/data/0" else d)
               for n, d in members]
    path = write_zip(tmp_path / "best_3.pth", members)
    with pytest.raises(PhysTwinFormatError, match=r"best_3\.pth"):
        load_torch_zip(path)
    bad_crc = write_zip(tmp_path / "best_4.pth", [(n, d) for n, d in members if n != "ok/data/0"]
                   + [("ok/data/0", (zlib.compress(record)[2:-4], 1234, len(record)))])
    with pytest.raises(PhysTwinFormatError, match=r"best_4\.pth"):
        load_torch_zip(bad_crc)


@pytest.mark.parametrize("data", [b"\x80\x02}q\x00(X\x03", b"\x80\x02\xff", b"", b"garbage bytes"])
def test_a_truncated_or_garbled_pickle_names_the_file(tmp_path, data):
    path = tmp_path / "optimal_params.pkl"
    path.write_bytes(data)
    with pytest.raises(PhysTwinFormatError, match=r"optimal_params\.pkl"):
        load_pickle(path)


def test_import_phystwin_reports_a_damaged_file_in_one_line(tmp_path, capsys):
    case = tmp_path / "case"
    case.mkdir()
    (case / "final_data.pkl").write_bytes(b"\x80\x02}q\x00(X\x03")  # cut short
    (case / "optimal_params.pkl").write_bytes(pickle.dumps({}, protocol=2))
    (case / "best_1.pth").write_bytes(b"PK\x03\x04" + b"\x00" * 40)
    assert cli(["import-phystwin", str(case), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "final_data.pkl: not a readable pickle" in err[0], err
