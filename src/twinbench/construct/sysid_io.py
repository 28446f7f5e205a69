"""System identification's files: the input (a sysid directory or a PhysTwin case) and the identified
object (a twin object directory).

    data = load_input("cases/rope")                     # sysid directory or PhysTwin final_data.pkl
    result = identify(data, FitConfig(cma=CMAConfig(budget=200)))   # twinbench.physics.sysid
    write_object_dir(result, data, "out/rope")          # object.json + npz
    write_report(result, data, "out")                   # twinbench.construct.sysid_report

A sysid directory holds ``sysid.json`` and the ``.npz`` it names (read with ``allow_pickle=False``)::

    sysid.json
    {"format": "twinbench-sysid", "version": 1, "name": "rope", "arrays": "data.npz",
     "fps": 30, "validation_frames": 10}

The ``.npz`` holds the arrays of :class:`~twinbench.physics.sysid_data.SysIdData` under their field names
(the table of keys, shapes and meanings is in ``twinbench.physics.sysid_data``). PhysTwin cases
(``final_data.pkl``) are read through the restricted loader of ``twinbench.construct.phystwin``, never
unpickled here.
"""

from __future__ import annotations

import json
from dataclasses import fields
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from twinbench.physics.params import SimParams
from twinbench.physics.sysid_data import OPTIONAL_ARRAYS, REQUIRED_ARRAYS, SysIdData, SysIdFormatError
from twinbench.twin.files import read_npz

if TYPE_CHECKING:
    from twinbench.physics.sysid import SysIdResult

FORMAT = "twinbench-sysid"
VERSION = 1
JSON_NAME = "sysid.json"


def _safe_relative(json_path: Path, key: str, rel) -> Path:
    if not isinstance(rel, str) or not rel:
        raise SysIdFormatError(f"{json_path}: field '{key}' must be a relative file path string, got {rel!r}")
    p = Path(rel)
    if p.is_absolute() or ".." in p.parts:
        raise SysIdFormatError(f"{json_path}: field '{key}' must be a path inside the directory "
                               f"(relative, no '..'), got {rel!r}")
    return json_path.parent / p


def load_sysid_data(path: str | Path) -> SysIdData:
    """Read a sysid directory (or its ``sysid.json``); see the module docstring for the format."""
    path = Path(path)
    json_path = path / JSON_NAME if path.is_dir() else path
    if not json_path.is_file():
        raise SysIdFormatError(f"{json_path}: not found; a sysid directory holds {JSON_NAME} and its .npz")
    try:
        meta = json.loads(json_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SysIdFormatError(f"{json_path}: not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise SysIdFormatError(f"{json_path}: must hold a JSON object")
    if meta.get("format") != FORMAT:
        raise SysIdFormatError(f"{json_path}: field 'format' must be {FORMAT!r}, got {meta.get('format')!r}")
    if meta.get("version") != VERSION:
        raise SysIdFormatError(f"{json_path}: field 'version' {meta.get('version')!r} is not supported "
                               f"(this twinbench reads version {VERSION})")
    unknown = set(meta) - {"format", "version", "name", "arrays", "fps", "validation_frames"}
    if unknown:
        raise SysIdFormatError(f"{json_path}: unknown field(s) {sorted(unknown)}")
    npz_path = _safe_relative(json_path, "arrays", meta.get("arrays"))
    if not npz_path.is_file():
        raise SysIdFormatError(f"{json_path}: field 'arrays' names {npz_path}, which does not exist")
    for key, kind in (("fps", (int, float)), ("validation_frames", int)):
        if key in meta and (isinstance(meta[key], bool) or not isinstance(meta[key], kind)):
            raise SysIdFormatError(f"{json_path}: field '{key}' must be a number, got {meta[key]!r}")
    try:  # the twin directories' bounded reader: headers first, plain numbers, declared sizes only
        arrays = read_npz(npz_path)
    except ValueError as exc:
        raise SysIdFormatError(f"{npz_path}: {exc}") from None
    except Exception as exc:  # noqa: BLE001 - a damaged archive (BadZipFile, zlib.error, EOFError, OSError)
        raise SysIdFormatError(f"{npz_path}: not a readable .npz ({type(exc).__name__}: {exc})") from None
    missing = [k for k in REQUIRED_ARRAYS if k not in arrays]
    if missing:
        raise SysIdFormatError(f"{npz_path}: missing array(s) {missing} (see twinbench.physics.sysid_data)")
    extra = set(arrays) - set(REQUIRED_ARRAYS) - set(OPTIONAL_ARRAYS)
    if extra:
        raise SysIdFormatError(f"{npz_path}: unknown array(s) {sorted(extra)}")
    kwargs = {k: arrays.get(k) for k in REQUIRED_ARRAYS + OPTIONAL_ARRAYS}
    return SysIdData(**kwargs, fps=meta.get("fps", 30.0), validation_frames=meta.get("validation_frames", 0),
                     name=meta.get("name", json_path.parent.name or "object"), source=str(npz_path))


def save_sysid_data(data: SysIdData, directory: str | Path, arrays: str = "data.npz") -> Path:
    """Write ``data`` as a sysid directory; returns the path of ``sysid.json``."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    np.savez(directory / arrays, **data.arrays())
    meta = {"format": FORMAT, "version": VERSION, "name": data.name, "arrays": arrays, "fps": data.fps,
            "validation_frames": data.validation_frames}
    path = directory / JSON_NAME
    path.write_text(json.dumps(meta, indent=2) + "\n")
    return path


def load_input(path) -> SysIdData:
    """A sysid directory (sysid.json + npz), or a PhysTwin case's `final_data.pkl` (or a folder holding
    one and no sysid.json), read through twinbench.construct.phystwin's restricted loader."""
    path = Path(path)
    pkl = path if path.suffix == ".pkl" else path / "final_data.pkl"
    if pkl.is_file() and not (path.is_dir() and (path / "sysid.json").is_file()):
        from twinbench.construct.phystwin import sysid_data_from_final_data

        return sysid_data_from_final_data(pkl)
    return load_sysid_data(path)


def sim_dict(sim: SimParams) -> dict:
    """SimParams as JSON-ready values (tuples as lists)."""
    return {f.name: (list(v) if isinstance(v := getattr(sim, f.name), tuple) else v) for f in fields(sim)}


def write_object_dir(result: SysIdResult, data: SysIdData, directory: str | Path) -> Path:
    """Write the identified object as a standalone twin object directory (``object.json`` + npz with
    explicit object springs, rest lengths, per-spring stiffness and masses; "sim" = the identified
    SimParams) through ``twinbench.twin.save_object``. Particles are the frame-0 positions with an
    identity rest pose (object frame = the observations' world frame). Returns object.json's path."""
    from twinbench.twin import ObjectSpec, save_object

    m = result.model
    n = m.num_object_springs
    obj = ObjectSpec(name=data.name, particles=m.x0_np.astype(np.float64),
                     springs=m.springs_np[:n].astype(np.int32),
                     rest_lengths=m.rest_lengths_np[:n].astype(np.float64), spring_Y=result.object_spring_Y,
                     mass=m.masses_np.astype(np.float64), binding="lbs")
    return save_object(obj, directory, sim=sim_dict(result.sim))
