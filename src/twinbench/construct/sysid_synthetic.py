"""A synthetic system-identification case with known answers (tests, benchmark, demos): an object with
hidden, spatially varying stiffness and hidden contact values, moved by control points and observed with
noise, occlusion and unreliable tracks."""

from __future__ import annotations

import math

import numpy as np

from twinbench.physics.model import ModelBuilder, lattice
from twinbench.physics.params import SimParams
from twinbench.physics.sysid import GlobalParams, rollout
from twinbench.physics.sysid_data import SysIdData


def synthetic_case(kind: str = "rope", *, frames: int = 40, validation_frames: int = 10, substeps: int = 40,
                   soft_Y: float = 300.0, stiff_Y: float = 3000.0, truth: GlobalParams | None = None,
                   noise: float = 1e-3, visible_fraction: float = 0.7, tracked_stride: int = 1,
                   seed: int = 0) -> tuple[SysIdData, dict]:
    """A ground-truth object with hidden, spatially varying stiffness (springs whose midpoint lies at
    x < the object's middle get ``soft_Y``, the others ``stiff_Y``) and hidden contact parameters
    (``truth``), lying on the ground, then lifted, stretched and swayed by two control points at each
    x end (as two hands would); observed at 30 Hz with ``noise`` (m, per axis), a random
    ``visible_fraction`` of the particles visible per frame, every ``tracked_stride``-th particle
    tracked (5 % of track samples motion-invalid).

    ``kind``: "rope" (20 particles 1 cm apart), "cloth" (8 x 4 sheet) or "plush" (6 x 3 x 3 block).
    ``substeps`` per 30 Hz frame (dt = 1 / (30 substeps)). Returns the data and the truth:
    {"params", "sim", "log_y" (all springs), "springs" (object springs), "positions" (noise-free,
    F x P x 3), "soft" (per object spring)}.
    """
    shapes = {"rope": (20, 1, 1), "cloth": (8, 4, 1), "plush": (6, 3, 3)}
    if kind not in shapes:
        raise ValueError(f"kind must be one of {sorted(shapes)}, got {kind!r}")
    rng = np.random.default_rng(seed)
    pts = lattice(*shapes[kind], spacing=0.01)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    ymid, zmid = 0.5 * (lo[1] + hi[1]), 0.5 * (lo[2] + hi[2])
    c0 = np.array([[lo[0] - 0.005, ymid, zmid - 0.005], [lo[0] - 0.005, ymid, zmid + 0.005],
                   [hi[0] + 0.005, ymid, zmid - 0.005], [hi[0] + 0.005, ymid, zmid + 0.005]])
    truth = truth or GlobalParams(spring_Y=stiff_Y, spring_radius=0.02, spring_max_neighbors=30,
                                  control_radius=0.02, control_max_neighbors=8, ground_restitution=0.1,
                                  ground_friction=0.8, drag_damping=1.0, dashpot_damping=50.0)
    base = SimParams(dt=1.0 / (30.0 * substeps), substeps=substeps)
    t = np.arange(frames) / 30.0
    u = np.clip(t / 0.6, 0.0, 1.0)
    u = u * u * (3.0 - 2.0 * u)  # smooth 0 -> 1 over 0.6 s: lift by 12 cm and pull the ends 3 cm apart
    sway = np.clip(t - 0.6, 0.0, None)  # then stretch and relax, and sway sideways
    stretch = 0.03 * u + 0.015 * np.sin(2.5 * sway)
    side = 0.03 * (1.0 - np.cos(2.0 * sway))
    controls = np.repeat(c0[None], frames, axis=0)
    controls[:, :, 1] += side[:, None]
    controls[:, :, 2] += 0.12 * u[:, None]
    controls[:, :2, 0] -= 0.5 * stretch[:, None]
    controls[:, 2:, 0] += 0.5 * stretch[:, None]
    b = ModelBuilder(truth.sim_params(base))
    b.add_body(pts, radius=truth.spring_radius, max_neighbors=truth.spring_max_neighbors)
    b.add_control_points(c0, radius=truth.control_radius, max_neighbors=truth.control_max_neighbors)
    model = b.finalize()
    n_obj = model.num_object_springs
    sp = model.springs_np[:n_obj]
    soft = 0.5 * (pts[sp[:, 0], 0] + pts[sp[:, 1], 0]) < 0.5 * (lo[0] + hi[0])
    log_y = np.full(model.num_springs, math.log(stiff_Y), np.float32)
    log_y[:n_obj][soft] = math.log(soft_Y)
    model.set_spring_log_y(log_y)
    xs = rollout(model, controls, frames - 1)[0].astype(np.float64)
    n = len(pts)
    observed = xs + rng.normal(0.0, noise, xs.shape)
    visibility = rng.random((frames, n)) < visible_fraction
    visibility[np.arange(frames), rng.integers(0, n, frames)] = True  # never an empty frame
    tracked_idx = np.arange(0, n, tracked_stride)
    tracked = xs[:, tracked_idx] + rng.normal(0.0, noise, (frames, tracked_idx.size, 3))
    motion_valid = rng.random((frames, tracked_idx.size)) >= 0.05
    data = SysIdData(pts, observed, visibility, tracked_idx, tracked, motion_valid, controls, fps=30.0,
                     validation_frames=validation_frames, name=kind)
    return data, {"params": truth, "sim": truth.sim_params(base), "log_y": log_y, "springs": sp,
                  "positions": xs, "soft": soft}
