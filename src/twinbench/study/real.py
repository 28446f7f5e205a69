"""The hidden "real" workcell of a study: a twin directory that plays the real world.

    real = make_real("push-t", seed=0, out=Path("study/real"))   # REAL/world/ + REAL/hidden.json

Derived from the task's built-in cell (the size's preset: "fast" for "small" and "medium", "reference" for
"full") but different from anything a reconstruction can assume, all drawn from `seed`:

- physics: the object has a finer particle layout than the cell's (model mismatch: no reconstruction can
  produce it), explicit springs whose stiffness varies over 3 spatial regions along the object's long
  axis (factors 0.3-3x the cell's), another total mass, ground friction / restitution, drag and dashpot
  damping, tool (and collider) friction, inelastic self contact; substeps as many as its stiffest springs
  and its dashpot on its lightest particles need;
- appearance: each camera has a `CameraResponse` (colour matrix + offset, gamma, white balance,
  vignetting, sensor noise, slight blur), and the robot's Gaussians are finer than the cell's;
- geometry: the cameras sit slightly off the cell's poses (known to a user only through calibration).

REAL/hidden.json holds every hidden value, and the values the evidence is made with (the scan's frame and
colour space, the calibration's error). Real rollouts are evaluations of REAL/world; the reconstruction
(`twinbench.study.reconstruct`) never opens REAL/.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from twinbench.errors import InputError
from twinbench.gaussians.response import CameraResponse
from twinbench.transforms import rotvec_to_matrix

FINER = 2.0 / 3.0  # the real object's lattice spacing relative to the cell's
ROBOT_GAUSSIAN_SPACING = 0.004  # m, the real robot's Gaussians (the cells' 0.006)
REGIONS = 3


def _cell_settings(task: str) -> tuple[type, str]:
    """(cell settings class, the field that sets its object's lattice spacing) of a built-in task."""
    from twinbench.twin.cells import PushTCell, RopeCell, ToyCell

    cells = {"push-t": (PushTCell, "particle_spacing"), "rope-routing": (RopeCell, "axial_spacing"),
             "toy-packing": (ToyCell, "spacing")}
    if task not in cells:
        raise InputError(f"study task: expected one of {sorted(cells)}, got {task!r}")
    return cells[task]


def preset_of(size) -> str:
    """The built-in cell preset of a study size (a name or a StudySize)."""
    from twinbench.study.sizes import study_size

    return study_size(size).preset


def task_cell(task: str, size, *, preset: str | None = None, **settings):
    """The task's built-in cell at the study size's preset (or `preset`), with cell `settings`, as a
    TwinSpec."""
    from twinbench.tasks import get_task

    _cell_settings(task)
    return get_task(task).task_cls(None).default_twin(preset or preset_of(size), **settings)


def _uniform(rng, lo, hi) -> float:
    return float(rng.uniform(lo, hi))


def _log_uniform(rng, lo, hi) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _small_rotation(rng, degrees: float) -> np.ndarray:
    axis = rng.normal(size=3)
    return rotvec_to_matrix(np.radians(degrees) * axis / np.linalg.norm(axis))


def perturbed_pose(pose: np.ndarray, rng, metres: float, degrees: float) -> np.ndarray:
    """`pose` moved by a random rotation of `degrees` and translation of `metres` (in its own frame)."""
    d = np.eye(4)
    d[:3, :3] = _small_rotation(rng, degrees)
    t = rng.normal(size=3)
    d[:3, 3] = metres * t / np.linalg.norm(t)
    return pose @ d


def stiffness_regions(particles: np.ndarray, springs: np.ndarray, regions: int = REGIONS):
    """Region index per spring: the springs' midpoints along the particles' principal axis, cut at the
    particles' quantiles into `regions` slabs. Returns (region per spring, axis, cut positions)."""
    centre = particles.mean(axis=0)
    _, _, vt = np.linalg.svd(particles - centre, full_matrices=False)
    axis = vt[0]
    along = (particles - centre) @ axis
    cuts = np.quantile(along, np.arange(1, regions) / regions)
    mid = 0.5 * (particles[springs[:, 0]] + particles[springs[:, 1]])
    return np.searchsorted(cuts, (mid - centre) @ axis), axis, cuts


def _response(rng) -> CameraResponse:
    return CameraResponse(
        matrix=np.eye(3) + rng.normal(0.0, 0.05, (3, 3)),
        offset=rng.uniform(-0.03, 0.03, 3),
        gamma=_uniform(rng, 0.85, 1.2),
        white_balance=rng.uniform(0.88, 1.12, 3),
        vignetting=_uniform(rng, 0.1, 0.3),
        noise_std=_uniform(rng, 1.0, 3.0),
        blur_sigma=_uniform(rng, 0.3, 0.8),
    )


def _scan_color_space(rng) -> np.ndarray:
    """A degree-2 colour map (see twinbench.gaussians.colormap): the phone scan's colours."""
    from twinbench.gaussians.colormap import identity_color_map

    m = identity_color_map(2)
    m[:, 0] = rng.uniform(-0.04, 0.04, 3)
    m[:, 1:4] = np.diag(rng.uniform(0.85, 1.1, 3)) + rng.normal(0.0, 0.03, (3, 3))
    m[:, 4:] = rng.normal(0.0, 0.03, (3, m.shape[1] - 4))
    return m


def object_rates(obj, dashpot: float) -> np.ndarray:
    """`physics.sysid.stability_rates` (omega, gamma) of an ObjectSpec's body (its explicit springs, or
    its radius rule) at the dashpot DASHPOT."""
    from twinbench.physics import SimParams
    from twinbench.physics.model import ModelBuilder
    from twinbench.physics.sysid import stability_rates

    rule = {"radius": obj.spring_radius, "max_neighbors": obj.max_neighbors} if obj.springs is None \
        else {"springs": obj.springs}
    b = ModelBuilder(SimParams())
    b.add_body(obj.particles, spring_Y=obj.spring_Y, mass=obj.mass, **rule)
    return np.asarray(stability_rates(b.finalize(), float(np.max(obj.spring_Y)), dashpot))


def make_real(task: str, seed: int, out: Path, size: str = "small") -> Path:
    """Write OUT/world/ (the real workcell, a twin directory) and OUT/hidden.json; returns OUT."""
    from twinbench.construct.sysid_io import sim_dict
    from twinbench.physics.model import radius_springs
    from twinbench.study.sizes import size_name
    from twinbench.twin import save_twin

    cls, spacing_field = _cell_settings(task)
    preset = preset_of(size)
    rng = np.random.default_rng(seed)
    nominal = task_cell(task, size)
    fine_spacing = getattr(cls.preset(preset), spacing_field) * FINER
    fine = task_cell(task, size, **{spacing_field: fine_spacing,
                                    "robot_gaussian_spacing": ROBOT_GAUSSIAN_SPACING})

    # the object: finer layout, explicit springs with regional stiffness, another mass
    base, obj = nominal.objects[0], fine.objects[0]
    pts = np.asarray(obj.particles, np.float64)
    springs = (radius_springs(pts, obj.spring_radius, obj.max_neighbors) if obj.springs is None
               else np.asarray(obj.springs))
    base_y = np.broadcast_to(np.asarray(obj.spring_Y, np.float64), (len(springs),)).copy()
    region, axis, cuts = stiffness_regions(pts, springs)
    factors = rng.permutation([_log_uniform(rng, 0.3, 0.55), _log_uniform(rng, 0.8, 1.25),
                               _log_uniform(rng, 1.8, 3.0)])
    spring_y = base_y * factors[region]
    nominal_mass = float(np.sum(np.broadcast_to(np.asarray(base.mass, np.float64), (base.num_particles,))))
    mass_factor = _log_uniform(rng, 0.6, 1.6)
    mass = mass_factor * nominal_mass / len(pts)

    sim0 = fine.sim
    sim = dataclasses.replace(
        sim0,
        ground_friction=float(np.clip(sim0.ground_friction * _uniform(rng, 0.7, 1.4), 0.05, 2.0)),
        ground_restitution=_uniform(rng, 0.0, 0.15),
        drag_damping=sim0.drag_damping * _uniform(rng, 0.5, 2.0),
        dashpot_damping=sim0.dashpot_damping * _uniform(rng, 0.5, 2.0),
        # a soft body's contact with itself is inelastic; with the cells' PhysTwin default 0.7 (or even 0.3)
        # the finer plush squeezed by the gripper buzzes (springs drive pinched pairs together at ~m/s a
        # substep, each substep bounces them apart: particles at 2-5 m/s while held, and one real episode
        # diverged). Not drawn, so the other draws of a seed are unchanged.
        object_restitution=0.0,
    )
    # substeps: the cell's preset, times how much faster the real object's stiffest springs and its dashpot
    # on lighter particles are than the cell's object's (each bound of `stability_rates` on its own: the
    # presets run below those conservative bounds, and a dashpot twice the cell's on particles a third of its
    # mass, stepped at the ratio of a combined bound, jittered: seed 4's T crept on along the table after a
    # push, and every push-T policy failed)
    frame_dt = sim0.dt * sim0.substeps

    real_obj = dataclasses.replace(obj, springs=springs.astype(np.int32), rest_lengths=None,
                                   spring_Y=spring_y, mass=mass)
    need = object_rates(real_obj, sim.dashpot_damping) / object_rates(base, sim0.dashpot_damping)
    substeps = max(sim0.substeps, math.ceil(sim0.substeps * float(np.max(need))))
    sim = dataclasses.replace(sim, substeps=substeps, dt=frame_dt / substeps)

    def friction(c):
        return dataclasses.replace(c, friction=float(np.clip(c.friction * _uniform(rng, 0.7, 1.4), 0.05, 2)))

    robot = dataclasses.replace(fine.robot, tool_contact=friction(fine.robot.tool_contact))
    colliders = tuple(dataclasses.replace(c, contact=friction(c.contact)) for c in fine.colliders)

    cameras, camera_truth = [], {}
    for cam in fine.cameras:
        metres, degrees = (0.003, 0.5) if cam.mount_link else (0.01, 1.0)
        pose = perturbed_pose(cam.pose, rng, metres, degrees)
        resp = _response(rng)
        cameras.append(dataclasses.replace(cam, pose=pose, response=resp))
        camera_truth[cam.name] = {"pose": pose.tolist(), "cell_pose": cam.pose.tolist(),
                                  "response": resp.to_dict()}

    real = dataclasses.replace(fine, name=f"real-{task}-{seed}", objects=(real_obj, *fine.objects[1:]),
                               robot=robot, colliders=colliders, cameras=tuple(cameras), sim=sim)
    out = Path(out)
    save_twin(real, out / "world")

    # what the evidence is made with: the scan's frame and colour space, the calibration's error
    scan_pose = np.eye(4)
    scan_pose[:3, :3] = _small_rotation(rng, _uniform(rng, 10.0, 40.0))
    scan_pose[:3, 3] = rng.uniform(-0.3, 0.3, 3)
    calibration_error = {
        cam.name: {"rotation_deg": 0.3, "translation_m": 0.003 if cam.mount_link is None else 0.002,
                   "intrinsics_rel": 0.005, "seed": int(rng.integers(2**31))}
        for cam in cameras
    }
    hidden = {
        "task": task, "seed": int(seed), "size": size_name(size), "preset": preset,
        "object": {
            "name": real_obj.name, "particles": len(pts), "cell_particles": base.num_particles,
            "spacing": fine_spacing, "cell_spacing": fine_spacing / FINER, "springs": len(springs),
            "regions": {"axis": axis.tolist(), "cuts": cuts.tolist(), "factors": factors.tolist(),
                        "springs_per_region": np.bincount(region, minlength=REGIONS).tolist()},
            "cell_spring_Y": float(np.median(base_y)), "mass_total": mass_factor * nominal_mass,
            "cell_mass_total": nominal_mass, "mass_factor": mass_factor,
        },
        "sim": sim_dict(sim), "cell_sim": sim_dict(nominal.sim),
        "tool_contact": dataclasses.asdict(robot.tool_contact),
        "cell_tool_contact": dataclasses.asdict(nominal.robot.tool_contact),
        "colliders": {c.name: dataclasses.asdict(c.contact) for c in colliders},
        "cameras": camera_truth,
        "scan": {"world_to_scan": scan_pose.tolist(), "color_map": {"degree": 2,
                                                            "coeffs": _scan_color_space(rng).tolist()}},
        "calibration_error": calibration_error,
        "robot_gaussian_spacing": ROBOT_GAUSSIAN_SPACING,
    }
    (out / "hidden.json").write_text(json.dumps(hidden, indent=1) + "\n")
    return out
