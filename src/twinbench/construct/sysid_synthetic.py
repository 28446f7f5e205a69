"""Synthetic system-identification cases with known answers (tests, benchmark, demos): an object with
hidden, spatially varying stiffness and hidden contact values, moved by control points (or pushed by a
tool) and observed with noise, occlusion and unreliable tracks."""

from __future__ import annotations

import math

import numpy as np

from twinbench.physics.model import ModelBuilder, lattice
from twinbench.physics.params import SimParams
from twinbench.physics.sysid import GlobalParams, rollout
from twinbench.physics.sysid_data import SysIdData
from twinbench.transforms import transform_points


def simulated_tracks(model, controls: np.ndarray, frames: int, rng: np.random.Generator, noise: float,
                     visible_fraction: float, tracked_idx: np.ndarray, tool: np.ndarray | None = None):
    """Roll `model` out under `controls` (and the kinematic `tool`'s world vertices per frame) and observe
    it as a tracker would: (positions, observed points with `noise`, visibility (each particle seen with
    `visible_fraction`, never an empty frame), the tracked points `tracked_idx` with noise, their motion
    validity (5 % dropped))."""
    xs = rollout(model, controls, frames - 1, tool=tool)[0].astype(np.float64)
    n = xs.shape[1]
    observed = xs + rng.normal(0.0, noise, xs.shape)
    visibility = rng.random((frames, n)) < visible_fraction
    visibility[np.arange(frames), rng.integers(0, n, frames)] = True  # never an empty frame
    tracked = xs[:, tracked_idx] + rng.normal(0.0, noise, (frames, tracked_idx.size, 3))
    motion_valid = rng.random((frames, tracked_idx.size)) >= 0.05
    return xs, observed, visibility, tracked, motion_valid


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
    tracked_idx = np.arange(0, len(pts), tracked_stride)
    xs, observed, visibility, tracked, motion_valid = simulated_tracks(model, controls, frames, rng, noise,
                                                                       visible_fraction, tracked_idx)
    data = SysIdData(pts, observed, visibility, tracked_idx, tracked, motion_valid, controls, fps=30.0,
                     validation_frames=validation_frames, name=kind)
    return data, {"params": truth, "sim": truth.sim_params(base), "log_y": log_y, "springs": sp,
                  "positions": xs, "soft": soft}


PHYSTWIN_ROPE_Y = (8e3, 6e4, 2.5e4)
"""the stiffness of the three regions along the rope (thirds by x), as the issue's PhysTwin rope"""


def phystwin_rope_case(*, seed: int = 0, nx: int = 20, frames: int = 45, validation_frames: int = 9,
                       noise: float = 1e-3, visible_fraction: float = 0.85) -> tuple[SysIdData, dict]:
    """A rope made with PhysTwin's conventions (unit masses, springs by the radius rule: 2 cm, at most 30
    neighbours, Y per unit strain; ground at z = 0; drag 2, dashpot 60; ground restitution 0.3, friction
    0.7) with three stiffness regions along it (:data:`PHYSTWIN_ROPE_Y`), an ``nx`` x 2 x 1 lattice at
    1 cm. Three hand points at its x = 0 end lift it 8 cm, drag it 10 cm along -x and 4 cm sideways and
    lower it 5 cm (the rope trails on the ground; lowered all the way, it folds where a 1 % stiffness error
    changes the shape by 3 cm), over ``frames`` frames at 30 Hz, simulated by
    twinbench's solver at twice the stable substeps. Observed with ``noise`` per axis, ``visible_fraction``
    of the particles per frame, every particle tracked (5 % of samples motion-invalid), the last
    ``validation_frames`` held out. Returns (data, truth): truth as :func:`synthetic_case`'s, with
    "region" (0, 1, 2 per object spring) instead of "soft"."""
    from twinbench.physics.sysid import stable_substeps

    rng = np.random.default_rng(seed)
    pts = lattice(nx, 2, 1, 0.01, origin=(0.0, 0.0, 0.005))
    hand0 = np.array([[-0.006, 0.005, 0.012], [-0.006, -0.004, 0.003], [-0.006, 0.014, 0.003]])
    t = np.arange(frames) / 30.0

    def smooth(a: float, b: float) -> np.ndarray:
        u = np.clip((t - a) / (b - a), 0.0, 1.0)
        return u * u * (3.0 - 2.0 * u)

    move = np.stack([-0.10 * smooth(0.35, 0.9), 0.04 * smooth(0.35, 0.9),
                     0.08 * smooth(0.0, 0.35) - 0.05 * smooth(0.9, 1.3)], axis=1)
    controls = hand0[None] + move[:, None, :]
    truth = GlobalParams(spring_Y=1.0, spring_radius=0.02, spring_max_neighbors=30, control_radius=0.02,
                         control_max_neighbors=10, ground_restitution=0.3, ground_friction=0.7,
                         drag_damping=2.0, dashpot_damping=60.0)

    def model_at(base: SimParams):
        b = ModelBuilder(truth.sim_params(base))
        b.add_body(pts, radius=truth.spring_radius, max_neighbors=truth.spring_max_neighbors)
        b.add_control_points(hand0, radius=truth.control_radius, max_neighbors=truth.control_max_neighbors)
        return b.finalize()

    model = model_at(SimParams())
    n_obj = model.num_object_springs
    sp = model.springs_np[:n_obj]
    mid_x = 0.5 * (pts[sp[:, 0], 0] + pts[sp[:, 1], 0])
    region = np.minimum((3 * (mid_x - pts[:, 0].min()) / np.ptp(pts[:, 0])).astype(int), 2)
    log_y = np.full(model.num_springs, math.log(PHYSTWIN_ROPE_Y[0]), np.float32)  # the hand holds region 0
    log_y[:n_obj] = np.log(np.asarray(PHYSTWIN_ROPE_Y)[region])
    substeps = 2 * stable_substeps(model, max(PHYSTWIN_ROPE_Y), truth.dashpot_damping, 30.0)
    base = SimParams(dt=1.0 / (30.0 * substeps), substeps=substeps)
    model = model_at(base)
    model.set_spring_log_y(log_y)
    n = len(pts)
    xs, observed, visibility, tracked, motion_valid = simulated_tracks(model, controls, frames, rng, noise,
                                                                       visible_fraction, np.arange(n))
    data = SysIdData(pts, observed, visibility, np.arange(n), tracked, motion_valid, controls, fps=30.0,
                     validation_frames=validation_frames, name="phystwin_rope")
    return data, {"params": truth, "sim": truth.sim_params(base), "log_y": log_y, "springs": sp,
                  "positions": xs, "region": region}


def pushed_block_case(*, tool_friction: float = 0.5, ground_friction: float = 0.5, frames: int = 36,
                      validation_frames: int = 6, substeps: int = 40, noise: float = 1e-3,
                      visible_fraction: float = 0.8, seed: int = 0, mesh_margin: float = 0.005,
                      gap: float = 0.006) -> tuple[SysIdData, dict]:
    """A 5 x 4 x 2 block (1 cm lattice, Y 3000) on the ground, pushed 7 cm along x and 5 cm along y by a
    1 x 2 x 3 cm box tool (``SysIdData.tool_*``, contact distance `mesh_margin`) whose face starts `gap`
    from its -x side: the tool slides along that face unless its friction holds the block, so how far the
    block follows the tool sideways and how far it turns depend on ``tool_friction``. No control points.
    Returns the data and the truth {"params", "sim", "positions"}."""
    import trimesh

    rng = np.random.default_rng(seed)
    pts = lattice(5, 4, 2, spacing=0.01)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    box = trimesh.creation.box((0.01, 0.02, 0.03))
    t = np.arange(frames) / 30.0
    u = np.clip((t - 0.1) / 0.9, 0.0, 1.0)
    u = u * u * (3.0 - 2.0 * u)
    poses = np.repeat(np.eye(4)[None], frames, axis=0)
    poses[:, 0, 3] = lo[0] - 0.005 - gap + 0.07 * u
    poses[:, 1, 3] = 0.5 * (lo[1] + hi[1]) + 0.05 * u
    poses[:, 2, 3] = 0.016
    truth = GlobalParams(spring_Y=3000.0, spring_radius=0.02, spring_max_neighbors=30, ground_restitution=0.0,
                         ground_friction=ground_friction, drag_damping=1.0, dashpot_damping=50.0,
                         tool_friction=tool_friction, tool_restitution=0.0)
    base = SimParams(dt=1.0 / (30.0 * substeps), substeps=substeps, mesh_margin=mesh_margin)
    tool = transform_points(poses, box.vertices)
    b = ModelBuilder(truth.sim_params(base))
    b.add_body(pts, radius=truth.spring_radius, max_neighbors=truth.spring_max_neighbors,
               spring_Y=truth.spring_Y)
    b.add_kinematic_mesh(tool[0], box.faces, restitution=truth.tool_restitution, friction=truth.tool_friction)
    model = b.finalize()
    tracked_idx = np.arange(len(pts))
    xs, observed, visibility, tracked, motion_valid = simulated_tracks(
        model, np.zeros((frames, 0, 3)), frames, rng, noise, visible_fraction, tracked_idx, tool)
    data = SysIdData(pts, observed, visibility, tracked_idx, tracked, motion_valid, np.zeros((frames, 0, 3)),
                     fps=30.0, validation_frames=validation_frames, name="block",
                     tool_vertices=box.vertices, tool_faces=box.faces, tool_poses=poses)
    return data, {"params": truth, "sim": truth.sim_params(base), "positions": xs}
