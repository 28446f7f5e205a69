"""Build a model from one of PhysTwin's golden NPZ files (``shared/reference/phystwin``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .model import ModelBuilder, SpringMassModel
from .params import SimParams

_REQUIRED = ("x0", "v0", "springs", "rest_lengths", "spring_logY_float32", "masses", "num_object_points",
             "num_control_points", "num_object_springs", "dt", "num_substeps", "dashpot_damping",
             "drag_damping", "gravity", "reverse_z", "spring_Y_min", "spring_Y_max", "collide_elas",
             "collide_fric", "object_collision", "collide_object_elas", "collide_object_fric",
             "collision_dist", "self_collision")


def load_golden(path: str | Path) -> dict[str, np.ndarray]:
    """Read a golden NPZ (no pickles) and check its input fields."""
    path = Path(path)
    with np.load(path, allow_pickle=False) as data:
        out = {k: data[k] for k in data.files}
    missing = [k for k in _REQUIRED if k not in out]
    if missing:
        raise ValueError(f"{path}: missing fields {missing}; is this a PhysTwin golden trajectory file?")
    if bool(out["reverse_z"]):
        raise ValueError(f"{path}: reverse_z=True is not supported (twinbench is z-up); flip the data")
    return out


def golden_params(g: dict[str, np.ndarray]) -> SimParams:
    return SimParams(
        dt=float(g["dt"]),
        substeps=int(g["num_substeps"]),
        gravity=tuple(float(x) for x in g["gravity"]),
        dashpot_damping=float(g["dashpot_damping"]),
        drag_damping=float(g["drag_damping"]),
        ground_restitution=float(g["collide_elas"]),
        ground_friction=float(g["collide_fric"]),
        object_collision=bool(g["object_collision"]),
        object_restitution=float(g["collide_object_elas"]),
        object_friction=float(g["collide_object_fric"]),
        collision_dist=float(g["collision_dist"]),
        self_collision=bool(g["self_collision"]),
        spring_Y_min=float(g["spring_Y_min"]),
        spring_Y_max=float(g["spring_Y_max"]),
    )


def golden_model(g: dict[str, np.ndarray], device: str = "cpu",
                 requires_grad: bool = False) -> SpringMassModel:
    """The model of a golden file: its explicit springs, rest lengths, float32 log Y and masks."""
    n = int(g["num_object_points"])
    n_obj = int(g["num_object_springs"])
    springs = g["springs"].astype(np.int64)
    masks = g["masks"] if "masks" in g else np.zeros(n, np.int32)
    b = ModelBuilder(golden_params(g))
    for body in np.unique(masks):
        idx = np.flatnonzero(masks == body)
        if not np.array_equal(idx, np.arange(idx[0], idx[0] + idx.size)):
            raise ValueError("golden masks must label contiguous particle ranges")
        sel = np.flatnonzero(np.isin(springs[:n_obj, 0], idx))
        b.add_body(g["x0"][idx], springs=springs[sel] - idx[0], rest_lengths=g["rest_lengths"][sel],
                   mass=g["masses"][idx], velocities=g["v0"][idx])
    if int(g["num_control_points"]):
        cs = springs[n_obj:]
        b.add_control_points(g["control_x0"], springs=np.stack([cs[:, 0] - n, cs[:, 1]], axis=1),
                             rest_lengths=g["rest_lengths"][n_obj:])
    model = b.finalize(device, requires_grad=requires_grad)
    if not np.array_equal(model.springs_np, g["springs"]):
        raise ValueError("golden spring order could not be reproduced (bodies must be listed in order)")
    model.set_spring_log_y(g["spring_logY_float32"])
    return model
