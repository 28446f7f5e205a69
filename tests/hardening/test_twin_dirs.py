"""Twin directories under hostile input (issue 25): every sim/controller number has a range checked at
load (NaN, infinities, negative counts, 1e9 substeps), .npz members are read only as far as their headers
declare and never beyond a cap (deflate bombs, huge shapes), complex arrays and deeply nested twin.json
are refused; each a TwinFormatError naming twin.json or the .npz and the field."""

from __future__ import annotations

import io
import json
import shutil

import numpy as np
import pytest
from bombs import GIB, peak_mb, write_zip, zeros_bomb

from twinbench.cli import main as cli
from twinbench.twin import TwinFormatError, load_twin, save_twin
from twinbench.twin.cells import push_t_cell


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    return save_twin(push_t_cell("fast"), tmp_path_factory.mktemp("twin") / "good").parent


def _copy(good, tmp_path, edit=None):
    root = tmp_path / "twin"
    shutil.copytree(good, root)
    if edit is not None:
        doc = json.loads((root / "twin.json").read_text())
        edit(doc)
        (root / "twin.json").write_text(json.dumps(doc))  # NaN / Infinity as Python's json writes them
    return root


FIELDS = [
    ("sim", "ground_friction", float("nan")), ("sim", "object_restitution", float("nan")),
    ("sim", "drag_damping", float("inf")), ("sim", "substeps", 10**9), ("sim", "substeps", 1e9),
    ("sim", "dt", 0.0), ("sim", "gravity", [0.0, 0.0, float("-inf")]), ("sim", "ground", 1),
    ("controller", "ik_max_iters", -5), ("controller", "control_hz", float("inf")),
    ("controller", "ik_restarts", 2.5), ("controller", "planar_quat", [0, 1, 0, float("nan")]),
]


@pytest.mark.parametrize(("section", "field", "value"), FIELDS, ids=[f"{s}.{f}={v}" for s, f, v in FIELDS])
def test_out_of_range_physics_and_controller_fields_are_named(good, tmp_path, section, field, value):
    root = _copy(good, tmp_path, lambda d: d[section].__setitem__(field, value))
    with pytest.raises(TwinFormatError) as err:
        load_twin(root)
    text = str(err.value)
    assert text.startswith(f"{root.resolve() / 'twin.json'}: {section}.{field}: expected "), text
    assert text.count("twin.json") == 1, text



@pytest.mark.parametrize("quat", [[0, 0, 0, 0], [0, 1, 0]])
def test_a_planar_quat_that_is_no_rotation_is_refused(good, tmp_path, quat):
    """All zeros passed the per-number range and made every planar target a NaN pose (audit of issue 25)."""
    root = _copy(good, tmp_path, lambda d: d["controller"].__setitem__("planar_quat", quat))
    with pytest.raises(TwinFormatError, match=r"twin\.json: controller: planar_quat: expected a wxyz quat"):
        load_twin(root)


def test_a_camera_mounted_on_a_link_the_robot_lacks_is_named_at_load(good, tmp_path):
    """A twin.json edited for another URDF (Panda's links) but keeping the built-in arm's camera mount."""

    def mount(doc):
        doc["cameras"][1]["mount_link"] = "panda_hand"

    root = _copy(good, tmp_path, mount)
    with pytest.raises(TwinFormatError) as err:
        load_twin(root)
    text = str(err.value)
    assert text.startswith(f"{root / 'twin.json'}: cameras[1].mount_link: 'panda_hand' is not a link of the "
                           "robot xarm7_pusher20.urdf (links: ['link_base', "), text


def test_twin_show_reports_a_nan_field_in_one_line(good, tmp_path, capsys):
    root = _copy(good, tmp_path, lambda d: d["sim"].__setitem__("ground_friction", float("nan")))
    assert cli(["twin", "show", str(root), "--out-dir", str(tmp_path / "png")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "sim.ground_friction: expected a number in [0, 2], got nan" in err[0], err


def _npy(shape, descr="<f8", data=b""):
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": descr, "fortran_order": False, "shape": shape})
    return buf.getvalue() + data


def _object_npz(root) -> str:
    doc = json.loads((root / "twin.json").read_text())
    return doc["objects"][0]["arrays"]


def _load_code(root) -> str:
    return ("from twinbench.twin import load_twin, TwinFormatError\n"
            f"try:\n    load_twin({str(root)!r})\n    print('loaded')\n"
            "except TwinFormatError as e:\n    print('refused:', e)")


def test_an_npz_member_declaring_gigabytes_is_refused_before_it_is_read(good, tmp_path):
    root = _copy(good, tmp_path)
    npz = _object_npz(root)
    n = 3 * GIB // 24
    header = _npy((n, 3))
    write_zip(root / npz, [("particles.npy", zeros_bomb(3 * GIB, header))])  # 3 GiB of zeros, a few kB
    peak, said = peak_mb(_load_code(root))
    assert said.startswith("refused:") and f"{npz} declares arrays beyond 1024 MiB" in said, said
    assert peak < 600, peak


def test_an_npz_member_that_inflates_beyond_its_header_is_read_only_as_declared(good, tmp_path):
    root = _copy(good, tmp_path)
    npz = _object_npz(root)
    with np.load(root / npz) as z:
        arrays = {k: z[k] for k in z.files}
    members = [(f"{k}.npy", _npy(v.shape, v.dtype.str, v.tobytes())) for k, v in arrays.items()
               if k != "particles"]
    p = arrays["particles"]
    members.append(("particles.npy", zeros_bomb(3 * GIB, _npy(p.shape, p.dtype.str, p.tobytes()))))
    write_zip(root / npz, members)  # the right particles, then 3 GiB of zeros nobody declared
    peak, said = peak_mb(_load_code(root))
    assert said == "loaded" and peak < 600, (said, peak)


def test_a_shape_of_1e12_rows_is_refused_without_memory_error(good, tmp_path):
    root = _copy(good, tmp_path)
    npz = _object_npz(root)
    write_zip(root / npz, [("particles.npy", _npy((10**12, 3), data=b"\0" * 96))])
    with pytest.raises(TwinFormatError, match=r"declares arrays beyond 1024 MiB \(array 'particles' of shape "
                                              r"\(1000000000000, 3\)\)"):
        load_twin(root)


@pytest.mark.parametrize("dtype", ["<c16", "<U4", "|V8"])
def test_arrays_that_are_not_plain_numbers_are_refused(good, tmp_path, dtype):
    root = _copy(good, tmp_path)
    npz = _object_npz(root)
    with np.load(root / npz) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["particles"] = arrays["particles"].astype(dtype) if dtype != "|V8" else \
        np.zeros(arrays["particles"].shape, dtype)
    np.savez(root / npz, **arrays)
    with pytest.raises(TwinFormatError, match=rf"{npz} has array 'particles' of dtype"):
        load_twin(root)


def test_a_damaged_npy_header_names_the_file(good, tmp_path):
    root = _copy(good, tmp_path)
    npz = _object_npz(root)
    bad = _npy((4, 3)).replace(b"'shape': (4, 3)", b"'shape': (4, 3")
    write_zip(root / npz, [("particles.npy", bad)])
    with pytest.raises(TwinFormatError, match=rf"{npz} has no readable .npy header for array 'particles'"):
        load_twin(root)


def test_a_twin_json_nested_100000_deep_is_refused(good, tmp_path):
    root = _copy(good, tmp_path)
    (root / "twin.json").write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(TwinFormatError, match=r"twin\.json: nested too deeply"):
        load_twin(root)


@pytest.mark.parametrize("value", [1e30, float("nan")])
def test_particles_far_from_the_origin_are_refused(good, tmp_path, value):
    """Found by the fuzzer: a particle at 1e30 m loaded and then failed the build (SVD did not converge)."""
    root = _copy(good, tmp_path)
    npz = _object_npz(root)
    with np.load(root / npz) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["particles"][3, 1] = value
    np.savez(root / npz, **arrays)
    with pytest.raises(TwinFormatError, match=r"particles must be finite and within 1000 m of the origin"):
        load_twin(root)
