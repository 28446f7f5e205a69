"""Real-to-sim construction commands (DESIGN §1 steps 2-5): one tyro config + main per command.

    twinbench segment SCAN.ply --boxes boxes.json --out seg/
    twinbench align-robot seg/robot.ply --urdf builtin:xarm7_gripper --out aligned/ --also seg/background.ply
    twinbench align-color --pairs pairs/ --gaussians aligned/robot.ply aligned/background.ply --out color/
    twinbench import-phystwin CASE_DIR --out objects/rope        (export-phystwin OBJECT_DIR --out CASE_DIR)
    twinbench mesh-to-object block.obj --spacing 0.005 --out objects/block
    twinbench twin build twin_config.json --out my_twin/
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import tyro

from twinbench.gaussians.io import load_gaussians, save_gaussians


def _write_json(path: Path, doc) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1) + "\n")


# ------------------------------------------------------------------------------------------ segment


@dataclass(frozen=True)
class SegmentConfig:
    """Split a workcell scan into robot / background / named objects with crop boxes."""

    scan: Annotated[Path, tyro.conf.Positional]
    """3DGS scan (.ply/.splat/.spz)"""
    boxes: Path
    """boxes JSON: optional coarse transform, robot / object / bounds boxes (see twinbench.twin.segment)"""
    out: Path
    """output folder: robot.ply, background.ply, objects/NAME.ply, segments.npz, segments.json"""


def segment(cfg: SegmentConfig) -> int:
    from twinbench.twin.segment import load_boxes, segment_scan

    transform, robot, objects, bounds = load_boxes(cfg.boxes)
    scan, seg = segment_scan(load_gaussians(cfg.scan), robot, objects, bounds, transform)
    out = cfg.out
    out.mkdir(parents=True, exist_ok=True)
    files = {"robot": "robot.ply", "background": "background.ply"}
    save_gaussians(scan.subset(seg.robot), out / "robot.ply")
    save_gaussians(scan.subset(seg.background), out / "background.ply")
    arrays = {"robot": seg.robot, "background": seg.background, "dropped": seg.dropped}
    for name, idx in seg.objects.items():
        files[name] = f"objects/{name}.ply"
        (out / "objects").mkdir(exist_ok=True)
        save_gaussians(scan.subset(idx), out / files[name])
        arrays[f"object_{name}"] = idx
    np.savez(out / "segments.npz", **arrays)
    counts = {k: int(len(v)) for k, v in arrays.items()}
    _write_json(out / "segments.json", {"scan": str(cfg.scan), "transform": seg.transform.tolist(),
                                        "files": files, "counts": counts})
    print(" ".join(f"{k}={v}" for k, v in counts.items()))
    return 0


# ------------------------------------------------------------------------------------------ align-robot


@dataclass(frozen=True)
class AlignRobotConfig:
    """Register robot Gaussians to the URDF at a known configuration and label them by link."""

    robot: Annotated[Path, tyro.conf.Positional]
    """the robot's Gaussians (e.g. segment's robot.ply)"""
    out: Path
    """output folder: robot.ply (world frame), labels.npz, far.ply, report.json, and the --also files"""
    urdf: str = "builtin:xarm7_gripper"
    """URDF path or built-in name (builtin:xarm7_gripper, builtin:xarm7_pusher)"""
    q: tuple[float, ...] | None = None
    """joint configuration of the scan (default: the robot's home)"""
    scale: bool = False
    """also estimate a uniform scale (scans of unknown units)"""
    also: tuple[Path, ...] = ()
    """other parts of the same scan to move into the robot base frame (background, objects)"""
    max_distance: float = 0.02
    """Gaussians farther than this from every link after alignment go to far.ply, not to the robot (m)"""
    voxel: float = 0.012
    """global-registration voxel (m, robot units)"""
    seed: int = 0


def align_robot(cfg: AlignRobotConfig) -> int:
    from twinbench.twin.align_robot import RegistrationParams, gaussian_normals, register_robot
    from twinbench.twin.build import load_spec_robot
    from twinbench.twin.spec import RobotSpec

    model = load_spec_robot(RobotSpec(urdf=cfg.urdf))
    q = model.home_q if cfg.q is None else model.check_q(np.asarray(cfg.q, dtype=np.float64))
    cloud = load_gaussians(cfg.robot)
    params = RegistrationParams(estimate_scale=cfg.scale, voxel=cfg.voxel, seed=cfg.seed)
    res = register_robot(cloud.means, model, q, params, scan_normals=gaussian_normals(cloud))
    write_aligned_robot(cfg.out, cloud, res, q, cfg.urdf, cfg.max_distance, cfg.also)
    rep = res.report(cfg.max_distance)
    print(f"fitness={rep['fitness']:.4f} rmse={rep['rmse_m'] * 1e3:.2f}mm scale={rep['scale']:.4f} "
          f"labelled={rep['labelled']} dropped={rep['dropped_far']}")
    return 0


def write_aligned_robot(out: Path, cloud, res, q, urdf: str, max_distance: float, also=()) -> None:
    """robot.ply + labels.npz (labels int32 into `links`) + far.ply + report.json (+ aligned copies)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    moved = cloud.transform(res.transform)
    near = res.distances <= max_distance
    save_gaussians(moved.subset(near), out / "robot.ply")
    save_gaussians(moved.subset(~near), out / "far.ply")
    np.savez(out / "labels.npz", labels=res.labels[near].astype(np.int32), links=np.asarray(res.links))
    rep = res.report(max_distance)
    rep.update({"urdf": urdf, "q": np.asarray(q).tolist(), "links": list(res.links)})
    aligned = {}
    for path in also:
        p = Path(path)
        dst = out / "aligned" / p.name
        dst.parent.mkdir(exist_ok=True)
        save_gaussians(load_gaussians(p).transform(res.transform), dst)
        aligned[str(p)] = f"aligned/{p.name}"
    rep["aligned"] = aligned
    _write_json(out / "report.json", rep)


def read_aligned_robot(folder: Path) -> tuple:
    """(cloud, labels, links, q, urdf) of an align-robot output folder."""
    folder = Path(folder)
    rep = json.loads((folder / "report.json").read_text())
    with np.load(folder / "labels.npz", allow_pickle=False) as z:
        labels, links = z["labels"], [str(s) for s in z["links"]]
    return load_gaussians(folder / "robot.ply"), labels, links, rep["q"], rep["urdf"]


# ------------------------------------------------------------------------------------------ align-color


@dataclass(frozen=True)
class AlignColorConfig:
    """Fit the colour map rendered -> real (IRLS, Tukey) and apply it to Gaussians' base colours."""

    out: Path
    """output folder: color_map.json, grid.png, the mapped .ply files, pairs/ (when rendered here)"""
    pairs: Path | None = None
    """folder of NAME_render.png / NAME_real.png (+ NAME_mask.png) pairs"""
    scan: tuple[Path, ...] = ()
    """instead of --pairs: Gaussians (world frame) to render from the calibrated cameras ..."""
    calibration: Path | None = None
    """... camera calibration file (see twinbench.twin.calibration) ..."""
    real: Path | None = None
    """... and a folder of real images NAME.png, one per camera name"""
    gaussians: tuple[Path, ...] = ()
    """.ply files to map (each written to OUT/<name>.ply)"""
    degree: int = 2
    iterations: int = 50


def align_color(cfg: AlignColorConfig) -> int:
    import imageio.v3 as iio

    from twinbench.twin.align_color import before_after_grid, fit_pairs, load_pairs

    cfg.out.mkdir(parents=True, exist_ok=True)
    if cfg.pairs is None:
        if not (cfg.scan and cfg.calibration and cfg.real):
            raise SystemExit(
                "align-color: give --pairs DIR, or --scan, --calibration and --real to render pairs"
            )
        pairs_dir = cfg.out / "pairs"
        render_pairs(cfg.scan, cfg.calibration, cfg.real, pairs_dir)
    else:
        pairs_dir = cfg.pairs
    pairs = load_pairs(pairs_dir)
    fit = fit_pairs(pairs, degree=cfg.degree, iterations=cfg.iterations)
    _write_json(cfg.out / "color_map.json", fit.to_json())
    iio.imwrite(cfg.out / "grid.png", before_after_grid(pairs, fit.coeffs, fit.degree))
    from twinbench.gaussians.colormap import apply_color_map

    for p in cfg.gaussians:
        save_gaussians(apply_color_map(load_gaussians(p), fit.coeffs, fit.degree), cfg.out / Path(p).name)
    print(f"pairs={len(pairs)} iterations={fit.iterations} residual_sigma={fit.scale:.4f}")
    return 0


def render_pairs(scan_files, calibration: Path, real_dir: Path, out_dir: Path,
                 background=(0.0, 0.0, 0.0)) -> list[str]:
    """Render the Gaussians from each static calibrated camera (its output view) beside its real image
    REAL_DIR/NAME.png: writes OUT_DIR/NAME_render.png, NAME_real.png and NAME_mask.png (pixels the scan
    covers, alpha > 0.99). Returns the camera names."""
    import shutil

    import imageio.v3 as iio

    from twinbench.gaussians.camera import Camera
    from twinbench.gaussians.cloud import GaussianCloud
    from twinbench.gaussians.render import render
    from twinbench.twin.align_color import read_image
    from twinbench.twin.calibration import load_calibration

    cloud = GaussianCloud.concatenate([load_gaussians(p) for p in scan_files])
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = []
    for cam in load_calibration(calibration):
        real = Path(real_dir) / f"{cam.name}.png"
        if cam.mount_link is not None or not real.is_file():
            continue
        img = read_image(real)
        h, w = cam.output_hw
        if img.shape[:2] != (h, w):
            raise ValueError(f"{real}: size {img.shape[:2]} differs from camera output_hw {(h, w)}")
        fx, fy, cx, cy = cam.output_intrinsics()
        out = render(cloud, [Camera(fx, fy, cx, cy, w, h, cam.pose)], background=background)[0]
        iio.imwrite(out_dir / f"{cam.name}_render.png", out.rgb_uint8())
        iio.imwrite(out_dir / f"{cam.name}_mask.png", ((out.alpha > 0.99) * 255).astype(np.uint8))
        shutil.copyfile(real, out_dir / f"{cam.name}_real.png")
        names.append(cam.name)
    if not names:
        raise ValueError(f"{real_dir}: no real image NAME.png for any static camera of {calibration}")
    return names


# ------------------------------------------------------------------------------------------ PhysTwin


@dataclass(frozen=True)
class ImportPhysTwinConfig:
    """Import a trained PhysTwin case (final_data.pkl, optimal_params.pkl, best_*.pth) as a twin object."""

    case_dir: Annotated[Path, tyro.conf.Positional]
    """case folder holding final_data.pkl, optimal_params.pkl and best_EPOCH.pth (or train/best_EPOCH.pth)"""
    out: Path
    """object folder to write (object.json + arrays + phystwin.npz/json for export)"""
    name: str = "object"
    final_data: Path | None = None
    optimal_params: Path | None = None
    checkpoint: Path | None = None
    reverse_z: bool = True
    """the case uses PhysTwin's reverse_z frame (its real-data configs do)"""
    self_collision: bool = False
    """the case was trained with self_collision (PhysTwin's cloth config)"""
    gaussians: Path | None = None
    """optional object Gaussians in the case's frame (PhysTwin's gaussian_output .ply)"""


def import_phystwin(cfg: ImportPhysTwinConfig) -> int:
    from twinbench.twin.phystwin import case_arrays, case_metadata, import_case, read_case

    case = read_case(cfg.case_dir, final_data=cfg.final_data, optimal_params=cfg.optimal_params,
                     checkpoint=cfg.checkpoint)
    imp = import_case(case, reverse_z=cfg.reverse_z, self_collision=cfg.self_collision)
    g = None if cfg.gaussians is None else load_gaussians(cfg.gaussians).transform(imp.frame)
    meta = case_metadata(case, imp, cfg.reverse_z)
    write_imported_object(cfg.out, cfg.name, imp, g, case_arrays(case), meta)
    print(f"particles={len(imp.particles)} springs={len(imp.springs)} "
          f"controller_springs={len(imp.controller_springs)} -> {cfg.out}")
    return 0


def write_imported_object(out: Path, name: str, imp, gaussians, arrays: dict, meta: dict) -> None:
    from twinbench.twin import ObjectSpec, save_object

    obj = ObjectSpec(name, imp.particles, springs=imp.springs, rest_lengths=imp.rest_lengths,
                     spring_Y=imp.spring_Y.astype(np.float64), mass=1.0, gaussians=gaussians, binding="lbs")
    save_object(obj, out, sim=imp.sim)
    np.savez(Path(out) / "phystwin.npz", **arrays)
    _write_json(Path(out) / "phystwin.json", meta)


@dataclass(frozen=True)
class ExportPhysTwinConfig:
    """Write a twin object imported from PhysTwin back as a PhysTwin case folder."""

    object_dir: Annotated[Path, tyro.conf.Positional]
    out: Path
    """case folder: final_data.pkl, optimal_params.pkl, train/best_EPOCH.pth"""


def export_phystwin(cfg: ExportPhysTwinConfig) -> int:
    from twinbench.twin.phystwin import case_from_arrays, write_case

    side, meta_path = cfg.object_dir / "phystwin.npz", cfg.object_dir / "phystwin.json"
    if not side.is_file() or not meta_path.is_file():
        raise SystemExit(
            f"export-phystwin: {cfg.object_dir} has no phystwin.npz/phystwin.json (only objects written by "
            "import-phystwin carry the case's tracking data PhysTwin needs)"
        )
    with np.load(side, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    final, op, ck, epoch = case_from_arrays(arrays, json.loads(meta_path.read_text()))
    paths = write_case(cfg.out, final, op, ck, epoch=epoch)
    print(" ".join(str(p) for p in paths.values()))
    return 0


# ------------------------------------------------------------------------------------------ mesh-to-object


@dataclass(frozen=True)
class MeshToObjectConfig:
    """A rigid (very stiff) spring-mass object from a closed mesh, with surface Gaussians."""

    mesh: Annotated[Path, tyro.conf.Positional]
    """closed mesh (.obj/.stl/.ply), metres"""
    out: Path
    spacing: float = 0.005
    """particle lattice spacing (m)"""
    name: str = "object"
    spring_Y: float = 3e4
    radius_factor: float = 1.9
    """springs within radius_factor x spacing"""
    max_neighbors: int = 50
    rgb: tuple[float, float, float] = (0.6, 0.6, 0.6)
    """Gaussian colour"""


def mesh_to_object_cmd(cfg: MeshToObjectConfig) -> int:
    from twinbench.twin import save_object
    from twinbench.twin.mesh_object import load_mesh, mesh_to_object

    obj = mesh_to_object(load_mesh(cfg.mesh), name=cfg.name, spacing=cfg.spacing, spring_Y=cfg.spring_Y,
                         radius_factor=cfg.radius_factor, max_neighbors=cfg.max_neighbors, rgb=cfg.rgb)
    save_object(obj, cfg.out, sim={})
    print(f"particles={obj.num_particles} gaussians={len(obj.gaussians)} -> {cfg.out}")
    return 0


# ------------------------------------------------------------------------------------------ twin build

_BUILD_FIELDS = {"name", "robot", "background", "objects", "colliders", "cameras", "sim", "controller",
                 "render"}
_ROBOT_PASS = {"ee_link", "contact_links", "gripper_joint", "gripper_open", "gripper_closed", "home_q",
               "scan_spacing"}


def _color_map_file(root: Path, value, where: str):
    from twinbench.twin import ColorMap

    if value is None:
        return None
    doc = json.loads((root / value).read_text())
    try:
        return ColorMap(int(doc["degree"]), np.asarray(doc["coeffs"], dtype=np.float64))
    except (KeyError, ValueError, TypeError) as exc:
        raise ValueError(f"{root / value}: {where}: not a colour map {{degree, coeffs}} ({exc})") from exc


def _known(d: dict, allowed: set, where: str, config: Path) -> dict:
    if not isinstance(d, dict):
        raise ValueError(f"{config}: {where} must be an object")
    unknown = set(d) - allowed
    if unknown:
        raise ValueError(f"{config}: {where}: unknown field(s) {sorted(unknown)}; known: {sorted(allowed)}")
    return d


def build_spec_from_config(config_path):
    """The TwinSpec described by a build config (JSON; paths relative to its folder):

        {"name": "my-cell",
         "robot": {"aligned": "aligned/" | null, "urdf": "builtin:xarm7_gripper" (default: the aligned
                   folder's), "color_map": "color/color_map.json" | null, "tool_contact": {...},
                   ee_link, contact_links, gripper_joint, gripper_open, gripper_closed, home_q, scan_spacing},
         "background": {"gaussians": "aligned/aligned/background.ply" | null, "color_map": null},
         "objects": [{"dir": "objects/tblock", "rest_pose": 4x4 | null,
                      "gaussians": "world-frame .ply replacing the object's own" | null, "color_map": null}],
         "colliders": [{"name", "mesh", "pose", "restitution", "friction", "gaussians"}],
         "cameras": "calibration.json",
         "sim": {SimParams fields over the first object's}, "controller": {...},
         "render": {"background": rgb}}
    """
    import dataclasses

    from twinbench.physics import SimParams
    from twinbench.robot.controller import ControllerConfig
    from twinbench.transforms import invert_pose
    from twinbench.twin import ColliderSpec, ContactSpec, RobotSpec, TwinSpec, load_object
    from twinbench.twin.calibration import load_calibration
    from twinbench.twin.mesh_object import load_mesh

    config = Path(config_path)
    root = config.parent
    try:
        doc = json.loads(config.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{config}: cannot read the build config ({exc})") from exc
    _known(doc, _BUILD_FIELDS, "top level", config)
    for req in ("robot", "objects", "cameras"):
        if req not in doc:
            raise ValueError(f"{config}: missing field {req!r}")

    r = _known(doc["robot"], _ROBOT_PASS | {"aligned", "urdf", "color_map", "tool_contact"}, "robot", config)
    kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in r.items() if k in _ROBOT_PASS}
    urdf = r.get("urdf")
    if r.get("aligned") is not None:
        cloud, labels, links, q, aligned_urdf = read_aligned_robot(root / r["aligned"])
        urdf = urdf or aligned_urdf
        kw.update(gaussians=cloud, gaussian_labels=labels, gaussian_links=tuple(links), gaussians_q=tuple(q))
    if not urdf:
        raise ValueError(f"{config}: robot.urdf is needed when robot.aligned is not given")
    if not str(urdf).startswith("builtin:"):
        urdf = str((root / urdf).resolve())
    if r.get("tool_contact") is not None:
        kw["tool_contact"] = ContactSpec(**r["tool_contact"])
    robot = RobotSpec(urdf=urdf, color_map=_color_map_file(root, r.get("color_map"), "robot.color_map"), **kw)

    bg = _known(doc.get("background") or {}, {"gaussians", "color_map"}, "background", config)
    background = load_gaussians(root / bg["gaussians"]) if bg.get("gaussians") else None

    objects, sim = [], {}
    for i, o in enumerate(doc["objects"]):
        o = _known(o, {"dir", "name", "rest_pose", "gaussians", "color_map"}, f"objects[{i}]", config)
        obj, osim = load_object(root / o["dir"])
        if i == 0:
            sim = dict(osim)
        changes = {}
        if o.get("name"):
            changes["name"] = o["name"]
        if o.get("rest_pose") is not None:
            changes["rest_pose"] = np.asarray(o["rest_pose"], dtype=np.float64)
        rest = changes.get("rest_pose", obj.rest_pose)
        if o.get("gaussians"):
            changes["gaussians"] = load_gaussians(root / o["gaussians"]).transform(invert_pose(rest))
        if o.get("color_map"):
            changes["color_map"] = _color_map_file(root, o["color_map"], f"objects[{i}].color_map")
        objects.append(dataclasses.replace(obj, **changes))

    colliders = []
    for i, c in enumerate(doc.get("colliders") or []):
        fields = {"name", "mesh", "pose", "restitution", "friction", "gaussians"}
        c = _known(c, fields, f"colliders[{i}]", config)
        mesh = load_mesh(root / c["mesh"])
        colliders.append(ColliderSpec(
            c["name"], np.asarray(mesh.vertices), np.asarray(mesh.faces),
            np.asarray(c.get("pose", np.eye(4)), dtype=np.float64),
            ContactSpec(c.get("restitution", 0.0), c.get("friction", 0.5)),
            load_gaussians(root / c["gaussians"]) if c.get("gaussians") else None,
        ))
    cams = doc["cameras"]
    if not isinstance(cams, str):
        raise ValueError(f"{config}: cameras must name a calibration file (see twinbench.twin.calibration)")
    cameras = load_calibration(root / cams)
    sim.update(doc.get("sim") or {})
    extra = {}
    if doc.get("render", {}).get("background") is not None:
        extra["render_background"] = tuple(doc["render"]["background"])
    known_sim = {f.name for f in dataclasses.fields(SimParams)}
    bad = sorted(set(sim) - known_sim)
    if bad:
        raise ValueError(f"{config}: sim: unknown SimParams field(s) {bad}")
    sim = {k: (tuple(v) if isinstance(v, list) else v) for k, v in sim.items()}
    ctrl = {k: (tuple(v) if isinstance(v, list) else v) for k, v in (doc.get("controller") or {}).items()}
    return TwinSpec(
        name=doc.get("name", config.stem), robot=robot, objects=tuple(objects), cameras=tuple(cameras),
        background=background, background_color_map=_color_map_file(root, bg.get("color_map"), "background"),
        colliders=tuple(colliders), sim=SimParams(**sim), controller=ControllerConfig(**ctrl), **extra,
    )


def build_from_config(config_path, out) -> Path:
    """`twinbench twin build CONFIG --out TWIN_DIR`: write the twin directory a build config describes."""
    from twinbench.twin import save_twin

    spec = build_spec_from_config(config_path)
    return save_twin(spec, out)
