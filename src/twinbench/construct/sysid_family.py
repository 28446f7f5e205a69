"""A seeded family of held-out system-identification cases: motion the fit's defaults were not tuned on.

`family_case(i, seed)` builds case ``i`` (any non-negative integer) from its own random stream: a particle
layout (rope, cloth, block or irregular blob), a spring radius (1.5 to 2.8 spacings), a hidden stiffness
pattern (two or three regions with factors, or a log-linear gradient along the object), hidden contact
and damping values, and an interaction (lift, drag along the ground, drop, poke); the motion is simulated
with finer substeps than a fit would use, then observed with noise (1 mm by default), partial visibility
and unreliable tracks, the last frames held out. Case ``i`` has layout ``i % 4`` and interaction
``(i + i // 4) % 4``: cases 0-11 hold each layout and each interaction three times, 0-15 every pair.
The truth says which motions slide (ground friction acts) and which hit the ground (restitution acts).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from twinbench.construct.sysid_synthetic import simulated_tracks
from twinbench.physics.model import ModelBuilder, lattice
from twinbench.physics.params import SimParams
from twinbench.physics.sysid import GlobalParams, rollout, stable_substeps
from twinbench.physics.sysid_data import SysIdData

LAYOUTS = ("rope", "cloth", "block", "irregular")
INTERACTIONS = ("lift", "drag", "drop", "poke")
SPACING = 0.01


def _layout(kind: str, rng: np.random.Generator) -> np.ndarray:
    """Particles resting on the ground (lowest at z = 1 mm), x along the object's long side."""
    if kind == "rope":
        pts = lattice(int(rng.integers(18, 27)), 1, 1, SPACING)
    elif kind == "cloth":
        pts = lattice(int(rng.integers(7, 10)), int(rng.integers(4, 6)), 1, SPACING)
    elif kind == "block":
        pts = lattice(int(rng.integers(5, 7)), 3, int(rng.integers(2, 4)), SPACING)
    else:  # a jittered blob: points in an ellipsoid at least 0.7 spacings apart
        axes = np.array([0.045, 0.025, 0.018])
        cand = rng.uniform(-1.0, 1.0, (4000, 3))
        cand = cand[np.sum(cand * cand, axis=1) <= 1.0] * axes
        keep: list[np.ndarray] = []
        for p in cand:
            if all(np.sum((p - q) ** 2) >= (0.7 * SPACING) ** 2 for q in keep):
                keep.append(p)
            if len(keep) >= 60:
                break
        pts = np.array(keep)
    pts = pts - pts.min(axis=0)
    return pts + np.array([0.0, 0.0, 0.001])


def _controls(kind: str, pts: np.ndarray, frames: int) -> np.ndarray:
    """(frames, K, 3) control trajectories of the interaction (K = 0 for a drop)."""
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    mid = 0.5 * (lo + hi)
    t = np.arange(frames) / 30.0
    ramp = np.clip(t / 0.5, 0.0, 1.0)
    ramp = ramp * ramp * (3.0 - 2.0 * ramp)
    if kind == "drop":
        return np.zeros((frames, 0, 3))
    if kind == "lift":  # one end up 10 cm and swayed, the other end hangs
        c0 = np.array([[lo[0] - 0.004, mid[1], mid[2] - 0.003], [lo[0] - 0.004, mid[1], mid[2] + 0.003]])
        move = np.stack([0.02 * np.sin(3.0 * t), 0.015 * np.sin(2.0 * t), 0.10 * ramp], axis=1)
    elif kind == "drag":  # one end pulled 10 cm along the ground and sideways
        c0 = np.array([[hi[0] + 0.004, mid[1] - 0.003, mid[2]], [hi[0] + 0.004, mid[1] + 0.003, mid[2]]])
        move = np.stack([0.10 * ramp, 0.03 * ramp * ramp, 0.004 * ramp], axis=1)
    else:  # poke: the middle pressed 1.5 cm down, then pulled 6 cm up and let hang
        c0 = np.array([[mid[0], mid[1], hi[2] + 0.004]])
        down = np.clip(t / 0.25, 0.0, 1.0) * np.clip((0.5 - t) / 0.25, 0.0, 1.0)
        move = np.stack([0 * t, 0 * t, -0.015 * down + 0.06 * np.clip((t - 0.5) / 0.3, 0.0, 1.0)], axis=1)
    return c0[None] + move[:, None, :]


def _stiffness(pattern: str, centres: np.ndarray, base_Y: float, rng: np.random.Generator) -> np.ndarray:
    """Per-spring stiffness from the springs' midpoints (x along the object)."""
    x = centres[:, 0]
    u = (x - x.min()) / max(np.ptp(x), 1e-9)
    if pattern == "gradient":
        factor = float(rng.uniform(5.0, 12.0))
        return base_Y * factor ** u
    n = 2 if pattern == "regions2" else 3
    factors = rng.permutation(np.geomspace(1.0, float(rng.uniform(5.0, 12.0)), n))
    return base_Y * factors[np.minimum((u * n).astype(int), n - 1)]


def _truth_model(pts: np.ndarray, controls: np.ndarray, truth: GlobalParams, sim: SimParams,
                 log_y: np.ndarray | None = None):
    """The hidden object: `pts` joined by the truth's spring rule, held by the controls' points, simulated
    with `sim`, stiffness `log_y` per spring (None: the builder's)."""
    b = ModelBuilder(sim)
    b.add_body(pts, radius=truth.spring_radius, max_neighbors=truth.spring_max_neighbors)
    if controls.shape[1]:
        b.add_control_points(controls[0], radius=truth.control_radius,
                             max_neighbors=truth.control_max_neighbors)
    model = b.finalize()
    if log_y is not None:
        model.set_spring_log_y(log_y)
    return model


def contact_effect(data: SysIdData, truth: dict, delta: float = 0.15) -> dict[str, float]:
    """How much the motion of a family case says about the ground's contact values, from the hidden truth:
    the RMS distance (m, over every particle and frame) between the noise-free motion and the same motion
    with the ground friction (resp. restitution) `delta` lower and `delta` higher (clipped to the search
    ranges, [0, 2] and [0, 1]), the larger of the two. Near 0 where the motion never slides (resp. never
    hits the ground hard enough to bounce): there no fit can recover the value within `delta`."""
    sim = truth["sim"]
    out = {}
    for name, hi in (("ground_friction", 2.0), ("ground_restitution", 1.0)):
        value = getattr(sim, name)
        moved = []
        for v in (max(value - delta, 0.0), min(value + delta, hi)):
            model = _truth_model(data.particles, data.controls, truth["params"], replace(sim, **{name: v}),
                                 truth["log_y"])
            xs = rollout(model, data.controls, len(data.controls) - 1)[0]
            moved.append(float(np.sqrt(np.mean(np.sum((xs - truth["positions"]) ** 2, axis=2)))))
        out[name.removeprefix("ground_")] = max(moved)
    return out


def step_effect(data: SysIdData, truth: dict, factors: tuple[float, ...] = (1.5, 2.0)) -> float:
    """How much a family case's motion depends on the time step, from the hidden truth: the validation
    tracking error (m, against the noisy tracks, as a fit's is measured) of the truth's own values simulated
    with each of ``factors`` times its substeps, the largest. Near the noise floor where the motion is
    converged in the time step; well above it where the motion is chaotic (a slip or a contact that a
    slightly other step resolves otherwise): there not even the truth's values track at the floor unless
    simulated at exactly the truth's step."""
    sim, errors = truth["sim"], []
    val = list(data.val_frames)
    for f in factors:
        substeps = max(1, round(f * sim.substeps))
        step = replace(sim, substeps=substeps, dt=sim.dt * sim.substeps / substeps)
        model = _truth_model(data.particles, data.controls, truth["params"], step, truth["log_y"])
        xs = rollout(model, data.controls, len(data.controls) - 1)[0]
        xt = xs[:, data.tracked_indices]
        errors.append(float(np.mean([np.mean(np.linalg.norm(xt[k][m] - data.tracked[k][m], axis=1))
                                     for k in val for m in [data.motion_valid[k]] if m.any()])))
    return max(errors)


def family_case(i: int, seed: int = 0, *, frames: int = 30, validation_frames: int = 6, noise: float = 1e-3,
                visible_fraction: float = 0.8) -> tuple[SysIdData, dict]:
    """Held-out case ``i`` of the family ``seed``. Returns (data, truth): truth holds "params"
    (GlobalParams: contact and damping values), "sim", "log_y" (all springs), "springs" (object springs),
    "positions" (noise-free), "layout", "interaction", "pattern", "slides", "impacts"."""
    rng = np.random.default_rng([int(seed), int(i), 29])
    layout = LAYOUTS[i % 4]
    interaction = INTERACTIONS[(i + i // 4) % 4]
    pattern = ("regions2", "regions3", "gradient")[int(rng.integers(0, 3))]
    pts = _layout(layout, rng)
    if interaction == "drop":
        pts = pts + np.array([0.0, 0.0, float(rng.uniform(0.03, 0.06))])
    controls = _controls(interaction, pts, frames)
    radius = float(rng.uniform(1.5, 2.8)) * SPACING
    truth = GlobalParams(
        spring_Y=1.0, spring_radius=radius, spring_max_neighbors=30, control_radius=0.015,
        control_max_neighbors=6, ground_restitution=float(rng.uniform(0.1, 0.6)),
        ground_friction=float(rng.uniform(0.3, 1.2)), drag_damping=float(rng.uniform(0.5, 3.0)),
        dashpot_damping=float(rng.uniform(10.0, 60.0)))
    model = _truth_model(pts, controls, truth, truth.sim_params(SimParams()))  # the springs
    n_obj = model.num_object_springs
    sp = model.springs_np[:n_obj]
    y = _stiffness(pattern, 0.5 * (pts[sp[:, 0]] + pts[sp[:, 1]]), math.exp(rng.uniform(math.log(150.0),
                                                                                             math.log(600.0))),
                   rng)
    log_y = np.full(model.num_springs, math.log(float(np.median(y))), np.float32)
    log_y[:n_obj] = np.log(y)
    substeps = 2 * stable_substeps(model, float(y.max()), truth.dashpot_damping, 30.0)
    base = SimParams(dt=1.0 / (30.0 * substeps), substeps=substeps)
    # the same springs (deterministic rule), finer substeps
    model = _truth_model(pts, controls, truth, truth.sim_params(base), log_y)
    tracked_idx = np.arange(len(pts))
    xs, observed, visibility, tracked, motion_valid = simulated_tracks(model, controls, frames, rng, noise,
                                                                       visible_fraction, tracked_idx)
    name = f"{layout}_{interaction}_{i}"
    data = SysIdData(pts, observed, visibility, tracked_idx, tracked, motion_valid, controls, fps=30.0,
                     validation_frames=validation_frames, name=name, springs=sp)
    low = xs[:, :, 2] < 0.003  # particles on (or pressed into) the ground
    speed = np.linalg.norm(np.diff(xs[:, :, :2], axis=0), axis=2) * 30.0
    slides = bool(np.any(low[1:] & (speed > 0.05)))
    vz = np.diff(xs[:, :, 2], axis=0) * 30.0
    impacts = bool(np.any((vz[:-1] < -0.3) & low[2:]))  # reaching the ground at > 0.3 m/s
    return data, {"params": truth, "sim": truth.sim_params(base), "log_y": log_y, "springs": sp,
                  "positions": xs, "layout": layout, "interaction": interaction, "pattern": pattern,
                  "slides": slides, "impacts": impacts, "substeps": substeps}
