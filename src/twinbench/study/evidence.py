"""Evidence of a hidden real workcell: what a user would have of it, in the formats the construction
commands read (and nothing else: no hidden value is written).

    ev = make_evidence(Path("study/real"), Path("study/evidence"), seed=0)

EV/ holds (EV/README.md lists them for the user):

- `scan.ply`: the workcell's Gaussians (robot at its home configuration, objects at rest, table and
  backdrop) in the scan's own frame: a random subset of the real scene's Gaussians (the scan is coarser),
  in another colour space, with position noise and floaters;
- `boxes.json`: the crop boxes and coarse scan -> world transform a user draws for `twinbench segment`
  (one box per object and per fixed collider, e.g. rope-routing's clip);
- `calibration.json`: each camera's intrinsics and pose (extrinsics or hand-eye), with realistic error;
- `real/NAME.png`: each static camera's real image of the workcell as scanned (its response, noise and
  blur included), to pair with renders of the scan for `twinbench align-color`;
- `motion/OBJECT/`: tracked motion of the object under a probe's interactions (lift, lower, drag) in the
  real workcell, in the sysid folder format (`twinbench.construct.sysid_io`): a coarse subset of its
  points as particles, subsampled noisy tracks with occlusion gaps, visibility-masked observed points;
- `motion/OBJECT-push/` (a robot with a pushing tool, not a gripper: push-T's pusher): the same, while the
  tool pushes the object along the table, in a direction that slides along the face it meets: the tool's
  path is in the sysid folder too (`tool_*`), its friction is not;
- `evidence.json`: the index of the above (task, size, robot URDF, object names, files).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from twinbench.study.sizes import size_name, study_size
from twinbench.transforms import invert_pose, transform_points

SCAN_KEEP = 0.5  # fraction of the real scene's Gaussians a scan sees
SCAN_NOISE = 0.0015  # m, per axis
FLOATERS = 0.01  # floaters per scan Gaussian
TRACK_NOISE = 0.001  # m, per axis, tracked and observed points
ROBOT_BOX = {"center": [0.1, 0.0, 0.56], "half_extents": [0.32, 0.3, 0.52]}


def _scene(real_spec, twin):
    """The real scene's Gaussians in the world frame, the robot at home, everything at rest."""
    from twinbench.gaussians.cloud import GaussianCloud
    from twinbench.twin.spec import with_color_map

    parts = [twin.robot_gaussians.posed(twin.robot.home_q)]
    parts += [o.rest_gaussians.transform(o.rest_pose) for o in real_spec.objects if o.gaussians is not None]
    parts += [with_color_map(c.gaussians, c.color_map).transform(c.pose)
              for c in real_spec.colliders if c.gaussians is not None]
    if real_spec.background is not None:
        parts.append(with_color_map(real_spec.background, real_spec.background_color_map))
    return GaussianCloud.concatenate(parts)


def make_scan(world, hidden: dict, rng):
    """The phone scan: a subset of `world`'s Gaussians, recoloured, noisy, with floaters, in its own frame."""
    from twinbench.gaussians.cloud import GaussianCloud
    from twinbench.gaussians.colormap import apply_color_map

    keep = np.sort(rng.choice(len(world), int(SCAN_KEEP * len(world)), replace=False))
    scan = world.subset(keep)
    cmap = hidden["scan"]["color_map"]
    scan = apply_color_map(scan, np.asarray(cmap["coeffs"]), int(cmap["degree"]))
    scan.means = scan.means + rng.normal(0.0, SCAN_NOISE, scan.means.shape).astype(np.float32)
    n = int(FLOATERS * len(scan))
    floaters = scan.subset(rng.integers(0, len(scan), n)).copy()
    lo, hi = scan.means.min(axis=0), scan.means.max(axis=0)
    floaters.means = rng.uniform(lo, hi, (n, 3)).astype(np.float32)
    floaters.sh[:, 0] = rng.normal(0.0, 1.0, floaters.sh[:, 0].shape).astype(np.float32)
    return GaussianCloud.concatenate([scan, floaters]).transform(np.asarray(hidden["scan"]["world_to_scan"]))


def _calibration(real_spec, hidden: dict) -> dict:
    """Each camera's calibration as a user's calibration would give it: pose and intrinsics with error."""
    from twinbench.construct.calibration import calibration_doc
    from twinbench.study.real import perturbed_pose

    cams = []
    for c in real_spec.cameras:
        err = hidden["calibration_error"][c.name]
        rng = np.random.default_rng(err["seed"])
        pose = perturbed_pose(c.pose, rng, err["translation_m"], err["rotation_deg"])
        k = np.asarray(c.intrinsics) * (1.0 + rng.normal(0.0, err["intrinsics_rel"], 4))
        cams.append(dataclasses.replace(c, pose=pose, intrinsics=tuple(k)))
    return calibration_doc(cams)


def _probe_path(points: np.ndarray, frames: int) -> np.ndarray:
    """(frames, 2, 3) probe points: gripping the object's top near one end of its long axis, lifting that
    end by 4 cm, lowering it, then dragging the object 4 cm sideways along the table."""
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd((points - centre)[:, :2], full_matrices=False)
    axis = np.array([*vt[0], 0.0])
    side = np.array([-axis[1], axis[0], 0.0])
    along = (points - centre) @ axis
    end = points[along > np.quantile(along, 0.85)]
    grip = np.array([*end[:, :2].mean(axis=0), end[:, 2].max() + 0.003])
    c0 = np.stack([grip - 0.006 * side, grip + 0.006 * side])
    t = np.linspace(0.0, 1.0, frames)

    def smooth(u):
        u = np.clip(u, 0.0, 1.0)
        return u * u * (3.0 - 2.0 * u)

    lift = 0.04 * (smooth(t / 0.3) - smooth((t - 0.35) / 0.25))
    drag = 0.04 * smooth((t - 0.6) / 0.35)
    path = np.repeat(c0[None], frames, axis=0)
    path[:, :, 2] += lift[:, None]
    path += (drag[:, None] * side)[:, None, :]
    return path


def _voxel_pick(points: np.ndarray, voxel: float) -> np.ndarray:
    """Indices of one point per occupied voxel (the one nearest the voxel's centre of mass)."""
    keys = np.floor(points / voxel).astype(np.int64)
    _, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    picks = []
    for v in range(inverse.max() + 1):
        idx = np.flatnonzero(inverse == v)
        c = points[idx].mean(axis=0)
        picks.append(idx[np.argmin(np.linalg.norm(points[idx] - c, axis=1))])
    return np.sort(np.asarray(picks))


def probe_motion(real_spec, obj, hidden: dict, rng, frames: int, validation: int):
    """Simulate the real object under the probe (physics directly, the real object's springs, masses and
    contact) and observe it as a tracker would. Returns (SysIdData, the real positions (F, P, 3))."""
    from twinbench.physics.model import ModelBuilder
    from twinbench.physics.sysid import rollout

    pts = transform_points(obj.rest_pose, np.asarray(obj.particles, np.float64))
    controls = _probe_path(pts, frames)
    b = ModelBuilder(real_spec.sim)
    b.add_body(pts, springs=obj.springs, rest_lengths=obj.rest_lengths, spring_Y=obj.spring_Y, mass=obj.mass)
    b.add_control_points(controls[0], radius=0.02, max_neighbors=10, spring_Y=float(np.median(obj.spring_Y)))
    xs = rollout(b.finalize(), controls, frames - 1)[0].astype(np.float64)[:, : len(pts)]
    return _observed(xs, hidden, rng, validation, obj.name, controls), xs


def _tool_mesh(robot) -> tuple[np.ndarray, np.ndarray]:
    """The robot's contact links' meshes at its home configuration, as one mesh (world vertices, faces)."""
    verts, faces, offset = [], [], 0
    for link in robot.contact_links:
        v = robot.contact_vertices(robot.home_q, link)
        verts.append(v)
        faces.append(np.asarray(robot.contact_faces(link)) + offset)
        offset += len(v)
    return np.concatenate(verts), np.concatenate(faces)


def _push_path(points: np.ndarray, tool: np.ndarray, frames: int) -> np.ndarray:
    """(frames, 3) translations of the tool (home orientation): its lowest point 5 mm above the table,
    6 mm behind the object's end along its long axis, then 5 cm along that axis and 6 cm sideways (so the
    tool slides along the face it meets unless friction holds the object) over 1 s after 0.1 s."""
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd((points - centre)[:, :2], full_matrices=False)
    axis = np.array([*vt[0], 0.0])
    side = np.array([-axis[1], axis[0], 0.0])
    tool_c = np.array([*tool[:, :2].mean(axis=0), tool[:, 2].min()])
    start = centre + (((points - centre) @ axis).min() - np.abs((tool - tool_c) @ axis).max() - 0.006) * axis
    start[2] = 0.005
    u = np.clip((np.arange(frames) / 30.0 - 0.1) / 1.0, 0.0, 1.0)
    u = u * u * (3.0 - 2.0 * u)
    return (start - tool_c)[None] + u[:, None] * (0.05 * axis + 0.06 * side)[None]


def push_motion(real_spec, robot, obj, hidden: dict, rng, frames: int, validation: int):
    """Simulate the real object pushed by the real robot's tool (`_push_path`; the real tool contact) and
    observe it as `probe_motion` does; the tool's mesh and path (with tracking noise) go in the data.
    Returns (SysIdData, the real positions (F, P, 3))."""
    from twinbench.physics.model import ModelBuilder
    from twinbench.physics.sysid import rollout

    pts = transform_points(obj.rest_pose, np.asarray(obj.particles, np.float64))
    verts, faces = _tool_mesh(robot)
    path = _push_path(pts, verts, frames)
    contact = real_spec.robot.tool_contact
    b = ModelBuilder(real_spec.sim)
    b.add_body(pts, springs=obj.springs, rest_lengths=obj.rest_lengths, spring_Y=obj.spring_Y, mass=obj.mass)
    b.add_kinematic_mesh(verts + path[0], faces, restitution=contact.restitution, friction=contact.friction)
    xs = rollout(b.finalize(), np.zeros((frames, 0, 3)), frames - 1, tool=verts[None] + path[:, None])[0]
    poses = np.repeat(np.eye(4)[None], frames, axis=0)
    poses[:, :3, 3] = path + rng.normal(0.0, 0.5 * TRACK_NOISE, path.shape)
    data = _observed(xs.astype(np.float64), hidden, rng, validation, obj.name, np.zeros((frames, 0, 3)),
                     tool_vertices=verts, tool_faces=faces, tool_poses=poses)
    return data, xs


def _observed(xs: np.ndarray, hidden: dict, rng, validation: int, name: str, controls: np.ndarray, **tool):
    """The SysIdData a tracker gives of the real positions `xs` (F, P, 3): a coarser particle layout, noisy
    observed points and tracks with gaps, `controls` with noise; `tool` (SysIdData's tool_* fields) as
    given."""
    from twinbench.physics.sysid_data import SysIdData

    frames = xs.shape[0]
    # a coarser layout than the real object's (one point per cell-spacing voxel) as the particles; where
    # that gives under half the cell's particles (a rope: its section is finer than the spacing along it,
    # and a 2-particle section slips out of the gripper), smaller voxels until it gives half or more
    voxel = hidden["object"]["cell_spacing"]
    chosen = _voxel_pick(xs[0], voxel)
    while len(chosen) < 0.5 * hidden["object"]["cell_particles"]:
        voxel *= 0.85
        chosen = _voxel_pick(xs[0], voxel)
    particles = xs[0, chosen] + rng.normal(0.0, 0.5 * TRACK_NOISE, (len(chosen), 3))
    # observed points: a fixed 60 % of the real points, each visible in 70 % of the frames
    seen = np.sort(rng.choice(xs.shape[1], int(0.6 * xs.shape[1]), replace=False))
    observed = xs[:, seen] + rng.normal(0.0, TRACK_NOISE, (frames, len(seen), 3))
    visibility = rng.random((frames, len(seen))) < 0.7
    visibility[np.arange(frames), rng.integers(0, len(seen), frames)] = True
    # tracks: every other particle, noisy, 5 % unreliable samples, and occlusion gaps of 4-10 frames
    tracked_idx = np.arange(0, len(chosen), 2)
    tracked = xs[:, chosen[tracked_idx]] + rng.normal(0.0, TRACK_NOISE, (frames, len(tracked_idx), 3))
    valid = rng.random((frames, len(tracked_idx))) >= 0.05
    for j in rng.choice(len(tracked_idx), max(1, len(tracked_idx) // 4), replace=False):
        start, length = int(rng.integers(1, frames - 4)), int(rng.integers(4, 11))
        valid[start:start + length, j] = False
    ctl = controls + rng.normal(0.0, 0.5 * TRACK_NOISE, controls.shape)
    return SysIdData(particles, observed, visibility, tracked_idx, tracked, valid, ctl, fps=30.0,
                     validation_frames=validation, name=name, **tool)


def make_evidence(real: Path, out: Path, seed: int = 0, size: str = "small") -> Path:
    """Write EV/ (see the module docstring) for the real workcell REAL (made by `make_real`); returns EV."""
    import imageio.v3 as iio

    from twinbench.construct._json import write_json
    from twinbench.construct.sysid_io import save_sysid_data
    from twinbench.gaussians.io import save_gaussians
    from twinbench.study.real import preset_of
    from twinbench.twin import build_twin, load_twin

    real, out = Path(real), Path(out)
    hidden = json.loads((real / "hidden.json").read_text())
    spec = load_twin(real / "world")
    twin, state = build_twin(spec)
    rng = np.random.default_rng(seed)
    out.mkdir(parents=True, exist_ok=True)

    save_gaussians(make_scan(_scene(spec, twin), hidden, rng), out / "scan.ply")
    # the user's coarse transform (about 1 deg, 1 cm off) and the boxes they draw in its frame
    from twinbench.study.real import perturbed_pose

    coarse = perturbed_pose(invert_pose(np.asarray(hidden["scan"]["world_to_scan"])), rng, 0.01, 1.0)
    boxes = {"transform": coarse.tolist(), "robot": ROBOT_BOX, "objects": {}}
    for o in spec.objects:  # around the object, from 4 mm above the table (below it: the table's Gaussians)
        pts = np.asarray(o.particles) @ o.rest_pose[:3, :3].T + o.rest_pose[:3, 3]
        lo, hi = pts.min(axis=0) - [0.02, 0.02, 0.0], pts.max(axis=0) + [0.02, 0.02, 0.01]
        lo[2] = max(lo[2], 0.004)
        boxes["objects"][o.name] = {"center": ((lo + hi) / 2).tolist(),
                                    "half_extents": ((hi - lo) / 2).tolist()}
    for c in spec.colliders:  # each fixed part (rope-routing's clip, toy-packing's box) gets its own box,
        # as wide as the objects' (the coarse transform is ~1 cm off: a tighter box would cut the part)
        pts = transform_points(c.pose, np.asarray(c.vertices, np.float64))
        lo, hi = pts.min(axis=0) - [0.02, 0.02, 0.0], pts.max(axis=0) + [0.02, 0.02, 0.01]
        lo[2] = max(lo[2], 0.004)
        boxes["objects"][c.name] = {"center": ((lo + hi) / 2).tolist(),
                                    "half_extents": ((hi - lo) / 2).tolist()}
    write_json(out / "boxes.json", boxes)
    write_json(out / "calibration.json", _calibration(spec, hidden))

    images = twin.render(state, [c.name for c in spec.cameras if c.mount_link is None])
    (out / "real").mkdir(exist_ok=True)
    for name, img in images.items():
        resp = spec.camera(name).response
        rgb = img.rgb_uint8()
        iio.imwrite(out / "real" / f"{name}.png", rgb if resp is None else resp.apply(rgb, rng))

    frames, validation = study_size(size).motion_frames
    motion, push = {}, {}
    for o in spec.objects:
        data, _ = probe_motion(spec, o, hidden, rng, frames, validation)
        save_sysid_data(data, out / "motion" / o.name)
        motion[o.name] = f"motion/{o.name}"
    # a pushing tool's push (a gripper's fingers hold by friction under the latch's normal force: a push
    # would not show the friction a grasp needs); after every probe, so their random draws are unchanged
    pusher = twin.robot.contact_links and twin.robot.gripper_joint is None
    for o in spec.objects if pusher else ():
        data, _ = push_motion(spec, twin.robot, o, hidden, rng, frames, validation)
        save_sysid_data(data, out / "motion" / f"{o.name}-push")
        push[o.name] = f"motion/{o.name}-push"
    index = {"task": hidden["task"], "size": size_name(size), "preset": preset_of(size),
             "urdf": spec.robot.urdf, "scan": "scan.ply", "boxes": "boxes.json",
             "calibration": "calibration.json", "real_images": "real",
             "objects": [o.name for o in spec.objects], "colliders": [c.name for c in spec.colliders],
             "motion": motion, "push": push}
    write_json(out / "evidence.json", index)
    (out / "README.md").write_text(README.format(
        task=hidden["task"], size=index["size"], urdf=spec.robot.urdf, objects=", ".join(motion),
        push=PUSH_README if push else "",
        frames=frames, colliders=", ".join(index["colliders"]) or "none", validation=validation))
    return out


PUSH_README = (
    "- `motion/OBJECT-push/`: the same while the robot's tool pushes the object along the table (the tool's\n"
    "  mesh and path as `tool_*` arrays: `twinbench sysid` fits its friction).\n"
)

README = """# Evidence of a {task} workcell ({size})

What a user has of the workcell, nothing more (`twinbench study reconstruct` rebuilds a twin from it):

- `scan.ply`: a Gaussian scan of the workcell in the scan's own frame (robot at its home configuration,
  objects at rest): noisy, with floaters, in the scanner's colour space.
- `boxes.json`: crop boxes (each object, each fixed part: {colliders}) and a coarse scan -> world
  transform for `twinbench segment`.
- `calibration.json`: camera intrinsics and poses (the static cameras' extrinsics, the wrist camera's
  hand-eye transform), from a calibration with realistic error.
- `real/NAME.png`: each static camera's image of the workcell as scanned, for `twinbench align-color`.
- `motion/OBJECT/`: tracked motion of each object ({objects}) while a probe lifts one end, lowers it and
  drags it sideways: {frames} frames at 30 Hz (the last {validation} held out), in the sysid folder format
  (`twinbench sysid --data motion/OBJECT`).
{push}- `evidence.json`: this list as data; the robot's URDF is `{urdf}`.
"""
