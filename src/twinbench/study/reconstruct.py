"""Reconstruction of a workcell from its evidence with the public CLI, as a user would run it, and the
study's ablation twins.

    twins = reconstruct(Path("study/evidence"), Path("study/twins"))   # {variant: twin directory}

The chain (each command printed as typed): `twinbench segment` (scan -> robot / background / objects),
`twinbench align-robot` (scan frame -> robot base frame, Gaussians labelled with links), `twinbench
refine-cameras` (the calibration corrected so that the scan's render lines up with each real image: the
twins' cameras), `twinbench align-color` (the scan's colours -> the real cameras' colours), `twinbench sysid`
(each object's physics from its tracked motion; once with the fit, once at its initial guess; with the fit,
the tool's friction, and the object's ground friction and drag where its probe left them unconstrained, from
a push recording, the object's other values held, adopted only where they track the push better and the push
constrains them, and the tool's contact distance measured from the push: `_push_fit`), then one build config
per variant and `twinbench twin build`. A fitted value goes into the twin only where its recording constrains
it (sysid's identifiability): elsewhere the task cell's (`open_values`, `adopt_push_fit`).
Between sysid and the build, the identified object (particles in the world frame) is put in its own frame at
the rest pose found by registering the task's object template to the segmented scan (`estimate_rest_pose`;
colours tell a rope's marked end from its other end), an object the task declares rigid laid on its template's
lattice (`template_layout`; its push fitted on that layout: `push_layout`); the task's public definition
supplies what the evidence does not hold: the object's outline and goal, the controller, the robot's control
conventions (which link the actions command, the gripper: `ROBOT_CONVENTIONS`) and the tool's contact (its
friction from the push recording in the fitted variants, when the evidence has one).

Fixed colliders (rope-routing's clip, toy-packing's box: evidence.json `colliders`): segmented by their own
crop box, aligned with the rest; the build config names each with the cell's mesh (written to
OUT/construction/colliders/NAME.obj), channel and contact (the task's public definition: the evidence has
no contact of them), its Gaussians from the scan (in its frame, colour-mapped as the rest), and its pose
found by registering the cell's collider to its scan Gaussians (`place_collider`), or the cell's declared
pose when the scan holds fewer than MIN_COLLIDER_GAUSSIANS of it (the log says which).

Variants (`VARIANTS`): "full"; "no-color" (identity colour map); "no-physics" (stiffness and contact at
sysid's initial guess, without its optimisation); "neither". Work files go to OUT/construction/.
"""

from __future__ import annotations

import dataclasses
import json
import shlex
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

# the public CLI in a process of its own, which ends when the study's does (however it ends: a study killed
# outright would leave a fit running for minutes, writing into the folder a run started again writes to)
_CLI = ("import sys\nfrom twinbench._runtime import watch_parent\nwatch_parent()\n"
        "from twinbench.cli import main\nsys.exit(main(sys.argv[1:]))")
VARIANTS = ("full", "no-color", "no-physics", "neither")
_COLOR = {"full": True, "no-color": False, "no-physics": True, "neither": False}
_PHYSICS = {"full": "fitted", "no-color": "fitted", "no-physics": "initial", "neither": "initial"}
# settings of the simulation that are the task cell's modelling choices, not the object's physics
# the robot's control conventions: which link the actions command (a gripper task's flange), the gripper,
# the home configuration. Like the controller, the task's public cell states them (a user knows them of their
# robot; no scan shows them): a twin built without them reads the same actions as another point's poses
ROBOT_CONVENTIONS = ("ee_link", "contact_links", "gripper_joint", "gripper_open", "gripper_closed", "home_q")
_CELL_SIM = ("object_collision", "self_collision", "collision_dist", "collision_exclusion",
             "max_collision_candidates", "candidate_radius_scale", "mesh_margin")


def _rot2(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s], [s, c]])


def estimate_rest_pose(observed: np.ndarray, template: np.ndarray, z: float = 0.0,
                       observed_rgb: np.ndarray | None = None,
                       template_rgb: np.ndarray | None = None) -> np.ndarray:
    """The planar pose (x, y, yaw; height `z`) that puts `template` (points in the object's frame) onto
    `observed` (world points of the object, floaters allowed): every 3 deg of yaw with the centroids
    matched, then trimmed 2D ICP from the best, polished on the capped symmetric distance. With colours
    (`observed_rgb`, `template_rgb`, (N, 3)): the half-turned fit is refined too, and when the shape cannot
    tell the two apart (a rope's straight tube: scores within 25 %), the one whose colours agree better
    (per channel correlation of the observed colours with their nearest template points' colours; any
    colour space) wins, e.g. the rope's marked end."""
    from scipy.optimize import minimize

    from twinbench.transforms import planar_pose

    obs = np.asarray(observed, np.float64)[:, :2]
    centre = np.median(obs, axis=0)
    dist = np.linalg.norm(obs - centre, axis=1)
    inlier = dist <= 2.5 * np.median(dist) + 1e-9
    obs = obs[inlier]
    tmpl = np.asarray(template, np.float64)[:, :2]
    rng = np.random.default_rng(0)
    few_obs = obs[rng.permutation(len(obs))[:1000]]  # the coarse search on at most 1000 points each
    few_tmpl = tmpl[rng.permutation(len(tmpl))[:1000]]
    tree_obs, tree_tmpl = cKDTree(obs), cKDTree(tmpl)
    c_obs, c_tmpl = obs.mean(axis=0), tmpl.mean(axis=0)

    def score(yaw, t):  # symmetric mean nearest distance (template -> scan, scan -> template)
        r = _rot2(yaw)
        return tree_obs.query(few_tmpl @ r.T + t)[0].mean() + tree_tmpl.query((few_obs - t) @ r)[0].mean()

    def capped(yaw, t):
        r = _rot2(yaw)
        return (np.minimum(tree_obs.query(few_tmpl @ r.T + t)[0], 0.01).mean()
                + np.minimum(tree_tmpl.query((few_obs - t) @ r)[0], 0.01).mean())

    def icp(yaw: float) -> tuple[float, np.ndarray]:
        t = c_obs - _rot2(yaw) @ c_tmpl
        for _ in range(15):  # trimmed ICP: the template's points matched to their nearest observed points
            moved = tmpl @ _rot2(yaw).T + t
            d, j = tree_obs.query(moved)
            keep = d <= np.quantile(d, 0.8)
            a, b = tmpl[keep], obs[j[keep]]
            ca, cb = a.mean(axis=0), b.mean(axis=0)
            h = (a - ca).T @ (b - cb)
            yaw = float(np.arctan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1]))
            t = cb - _rot2(yaw) @ ca
        # polish on the symmetric distance, each point's capped at 1 cm (floaters): the trimmed ICP drops
        # the worst-matched points, which for a long thin object (a rope) are its ends, all that fixes its
        # position along its axis
        res = minimize(lambda p: capped(p[2], p[:2]), np.r_[t, yaw], method="Nelder-Mead", options={
            "initial_simplex": np.r_[t, yaw] + np.vstack([np.zeros(3), np.diag([0.003, 0.003, 0.02])]),
            "xatol": 1e-5, "fatol": 1e-8, "maxfev": 300})
        return float(res.x[2]), np.asarray(res.x[:2])

    yaws = np.radians(np.arange(0.0, 360.0, 3.0))
    fits = [icp(min(yaws, key=lambda a: score(a, c_obs - _rot2(a) @ c_tmpl)))]
    if observed_rgb is not None and template_rgb is not None:
        fits.append(icp(fits[0][0] + np.pi))
        scores = [score(*f) for f in fits]
        if max(scores) <= 1.25 * min(scores):
            rgb_obs = np.asarray(observed_rgb, np.float64)[inlier]
            rgb_tmpl = np.asarray(template_rgb, np.float64)

            def agreement(fit) -> float:
                j = tree_tmpl.query((obs - fit[1]) @ _rot2(fit[0]))[1]
                return sum(np.nan_to_num(np.corrcoef(rgb_obs[:, k], rgb_tmpl[j, k])[0, 1]) for k in range(3))

            fits.sort(key=agreement, reverse=True)
        else:
            fits.sort(key=lambda f: score(*f))
    yaw, t = fits[0]
    pose = planar_pose(float(t[0]), float(t[1]), yaw)
    pose[2, 3] = z
    return pose


def _half_turn_symmetric(vertices: np.ndarray, tol: float = 1e-3) -> bool:
    """Whether a mesh's vertices map onto themselves under a half turn about its frame's z axis."""
    v = np.asarray(vertices, np.float64)
    turned = v * [-1.0, -1.0, 1.0]
    return bool(cKDTree(v).query(turned)[0].max() <= tol)


def place_collider(scanned: np.ndarray, collider) -> np.ndarray:
    """The pose of the task's fixed collider `collider` (a ColliderSpec: mesh, Gaussians, declared pose)
    registered to its segmented scan Gaussians `scanned` (world points). A collider that a half turn about
    its z axis leaves unchanged (the rope clip: the same walls, the same channel with its openings swapped)
    has two equally good poses: the one nearer the cell's declared heading is kept."""
    template = collider.gaussians.means if collider.gaussians is not None else collider.vertices
    pose = estimate_rest_pose(scanned, template, float(collider.pose[2, 3]))
    declared = np.arctan2(collider.pose[1, 0], collider.pose[0, 0])
    yaw = np.arctan2(pose[1, 0], pose[0, 0])
    if _half_turn_symmetric(collider.vertices) and abs(np.angle(np.exp(1j * (yaw - declared)))) > np.pi / 2:
        pose[:3, :3] = pose[:3, :3] @ np.diag([-1.0, -1.0, 1.0])
    return pose


def template_layout(identified, template, stiffness_known: bool = True) -> tuple[dict, dict]:
    """Where the task declares the object rigid (its template's `binding` "rigid": a made part whose shape is
    public, as push-T's T), the template's particles (a lattice over its shape at the cell's spacing, springs
    by its radius rule) with the identified object's total mass spread evenly and its median spring stiffness
    (`stiffness_known`: its motion constrains the stiffness; else the template's, as a rigid body's motion
    does not): the ObjectSpec fields to replace, and the record (particle counts, stiffness and where it is
    from, mass). A voxel pick of noisy tracks puts a coarse T's centre of mass off the real one and leaves
    parts of its outline without particles (docs/study.md). Any other object (a rope, a plush toy: its rest
    shape is what the scan shows) keeps the identified layout: ({}, its record)."""
    n = len(identified.particles)
    mass = float(np.sum(np.broadcast_to(np.asarray(identified.mass, np.float64), (n,))))
    record = {"layout": "identified", "particles": n, "mass": mass}
    if template.binding != "rigid":
        return {}, record
    source = identified if stiffness_known else template
    y = float(np.median(np.asarray(source.spring_Y, np.float64)))
    m = len(template.particles)
    fields = {"particles": np.asarray(template.particles, np.float64), "springs": None, "rest_lengths": None,
              "spring_Y": y, "spring_radius": template.spring_radius, "max_neighbors": template.max_neighbors,
              "mass": mass / m}
    return fields, {**record, "layout": "template", "particles": m, "identified_particles": n, "spring_Y": y,
                    "spring_Y_from": "identified" if stiffness_known else "template"}


# the object's contact and damping values a fit can leave open: where neither its recordings constrains one
# (sysid's identifiability), the twin takes the task cell's (the public prior; a flat fit's value is one draw
# of many and moves with the machine's rounding)
OPEN_SIM = ("ground_friction", "ground_restitution", "drag_damping", "dashpot_damping")


def constrains(report: dict, name: str, unknown: bool) -> bool:
    """Whether a `twinbench sysid` report (its JSON) says its motion constrains value `name` (its
    `identifiability`); `unknown` where it does not say (a fit without that search, a start as it is)."""
    entry = report.get("identifiability", {}).get(name)
    return unknown if entry is None else bool(entry.get("constrained", unknown))


def open_values(report: Path, cell_sim, chosen: dict) -> dict:
    """The task cell's values (`cell_sim`, SimParams) of those OPEN_SIM values that the probe fit (REPORT, a
    `twinbench sysid` report) leaves unconstrained, but those a push fit chose (`chosen`: {name: value}, its
    own rule: `adopt_push_fit`); a report without identifiability (its search off): none."""
    probe = json.loads(Path(report).read_text())
    return {k: float(getattr(cell_sim, k)) for k in OPEN_SIM
            if not constrains(probe, k, True) and k not in chosen}


def stiffness_known(report: Path) -> bool:
    """Whether a `twinbench sysid` report (REPORT, JSON) says its motion constrains the stiffness (a fit
    without that search, e.g. at the initial guess: True, its value is kept)."""
    return constrains(json.loads(Path(report).read_text()), "spring_Y", True)


def _place_object(identified: Path, template, rest_pose: np.ndarray, sim_over: dict, out: Path) -> dict:
    """The identified object (world-frame particles, from `twinbench sysid`) in its own frame at
    `rest_pose`, with the template's name, binding, outline and goal, its particles laid as
    `template_layout` says; its sim with `sim_over`. Returns the layout's record."""
    from twinbench.transforms import invert_pose, transform_points
    from twinbench.twin import load_object, save_object

    obj, sim = load_object(identified)
    placed = dataclasses.replace(
        obj, name=template.name, particles=transform_points(invert_pose(rest_pose), obj.particles),
        rest_pose=rest_pose, binding=template.binding, outline=template.outline, goal_pose=template.goal_pose,
    )
    fields, record = template_layout(placed, template, stiffness_known(identified / "report.json"))
    save_object(dataclasses.replace(placed, **fields), out, sim={**sim, **sim_over})
    return record


MIN_COLLIDER_GAUSSIANS = 50  # fewer scanned Gaussians of a fixed collider: the cell's declared pose


def robot_entry(robot, color_map: str | None, tool_contact: dict | None = None) -> dict:
    """The build config's robot: the aligned scan, the colour map, the cell's `ROBOT_CONVENTIONS`, and
    `tool_contact` (default: the cell's)."""
    conventions = json.loads(json.dumps({k: getattr(robot, k) for k in ROBOT_CONVENTIONS}))  # tuples: lists
    return {"aligned": "aligned", "color_map": color_map, **conventions,
            "tool_contact": tool_contact or dataclasses.asdict(robot.tool_contact)}


def _collider_entry(cell, name: str, scanned_file: Path, work: Path, log) -> dict:
    """The build config's entry for the cell's fixed collider `name` (the task's public definition gives its
    mesh, channel and contact; the scan its pose and Gaussians): writes WORK/colliders/NAME.obj (the mesh,
    collider frame) and WORK/colliders/NAME.ply (its scan Gaussians in the collider frame)."""
    from twinbench.errors import InputError
    from twinbench.gaussians.io import load_gaussians, save_gaussians
    from twinbench.transforms import invert_pose

    spec = next((c for c in cell.colliders if c.name == name), None)
    if spec is None:
        raise InputError(f"evidence collider {name!r}: the task's cell has colliders "
                         f"{[c.name for c in cell.colliders]}; name one of them in evidence.json 'colliders'")
    import trimesh

    out = work / "colliders"
    out.mkdir(parents=True, exist_ok=True)
    mesh = trimesh.Trimesh(np.asarray(spec.vertices), np.asarray(spec.faces), process=False)
    mesh.export(out / f"{name}.obj")
    scanned = load_gaussians(scanned_file) if scanned_file.is_file() else None
    if scanned is not None and len(scanned) >= MIN_COLLIDER_GAUSSIANS:
        pose, source = place_collider(scanned.means, spec), "the scan"
    else:  # the scan does not hold it (too few Gaussians in its box): the cell's declared pose
        pose, source = np.asarray(spec.pose, np.float64), "the cell's declared pose"
    log(f"# collider {name}: pose from {source} x={pose[0, 3]:.4f} y={pose[1, 3]:.4f} "
        f"yaw={np.degrees(np.arctan2(pose[1, 0], pose[0, 0])):.2f} deg")
    entry = {"name": name, "mesh": f"colliders/{name}.obj", "pose": pose.tolist(),
             "restitution": spec.contact.restitution, "friction": spec.contact.friction,
             "channel": None if spec.channel is None else list(spec.channel)}
    if scanned is not None and len(scanned):
        save_gaussians(scanned.transform(invert_pose(pose)), out / f"{name}.ply")
        entry["gaussians"] = f"colliders/{name}.ply"
    return entry


# what a push recording fits: the tool's friction, with the object's ground friction and drag where its
# probe fit left them unconstrained (both resist its sliding; a probe's lift and drag can trade one for the
# other)
PUSH_SEARCH = ("tool_friction", "ground_friction", "drag_damping")
PUSH_BUDGET = {1: 16, 2: 30, 3: 40}  # CMA-ES evaluations of the push fit, by the number of values it searches


def push_search(probe_report: dict) -> tuple[str, ...]:
    """The values a push fit searches: the tool's friction, and those of the object's ground friction and drag
    that its probe fit (`probe_report`, a `twinbench sysid` report) did not constrain (its `identifiability`:
    a value the probe's motion pins down keeps it)."""
    return ("tool_friction", *(n for n in PUSH_SEARCH[1:] if not constrains(probe_report, n, False)))


def push_fit_dir(names: tuple[str, ...], start: str) -> str:
    """The folder (under OUT/construction/sysid/push/OBJECT) of a push fit of `names` from `start`."""
    return f"{'-'.join(n.split('_')[0] for n in names)}-from-{start}"


def push_layout(push: Path, identified: Path, template, out: Path) -> tuple[Path, dict] | None:
    """For an object the task declares rigid (`template_layout`): the push recording PUSH carried onto the
    template's layout (`construct.rigid_layout.relayout`: every particle follows the tracks' rigid motion),
    the template registered to the push's frame-0 observed points (`estimate_rest_pose`), the identified
    object's (IDENTIFIED, its probe fit's object directory) total mass spread evenly; written to OUT (sysid
    format). Returns OUT and what a fit on it holds ({name: value}: the template's spring radius and
    neighbours, the identified median stiffness), or None for any other object."""
    from twinbench.construct.rigid_layout import relayout
    from twinbench.construct.sysid_io import load_sysid_data, save_sysid_data
    from twinbench.transforms import transform_points
    from twinbench.twin import load_object

    known = stiffness_known(identified / "report.json")
    fields, _ = template_layout(load_object(identified)[0], template, known)
    if not fields:
        return None
    data = load_sysid_data(push)
    pose = estimate_rest_pose(data.observed[0][data.visibility[0]], template.gaussians.means,
                              float(template.rest_pose[2, 3]))
    particles = transform_points(pose, fields["particles"])
    save_sysid_data(relayout(data, particles, np.full(len(particles), fields["mass"])), out)
    return out, {"spring_radius": fields["spring_radius"], "spring_max_neighbors": fields["max_neighbors"],
                 "spring_Y": fields["spring_Y"]}


def _push_fit(run, push: Path, probe: Path, report: Path, out: Path, mesh_margin: float, cell: dict,
              log: Callable[[str], None], layout: tuple[Path, dict] | None = None,
              sysid_flags: tuple[str, ...] = ()) -> dict:
    """`twinbench sysid` of a push recording: the tool's friction (in [0, 1.5]) and the object's ground
    friction and drag where its probe fit (`report`) left them unconstrained (`push_search`), the object's
    other global values held at that fit, the tool's contact distance measured from the push (`sysid
    --measure-mesh-margin`: the nearest observed point's distance to the tool while it carries the object;
    the fitted twins take it, a measurement, not a fit; `mesh_margin` the recordings without a tool). Two
    starts: the probe fit's values with the task cell's tool friction (`cell`: {name: value} of
    PUSH_SEARCH), and the cell's values (a probe fit in a corner of the ranges held the search there); of
    the fits and the second start itself, the one tracking the push's fitted frames best is kept
    (`best_push_point`). Adopted (`adopt_push_fit`) only when it tracks the push better than the cell's values
    (what the twin has otherwise: values its probe left open, and the cell's tool) on the fitted and the
    held-out frames, and then only the values that fit constrains (its identifiability); else the tool's
    friction alone is fitted under the same rule; else the cell's values are kept. `layout` (`push_layout`'s):
    the push fitted on that recording instead, with the values it holds. Where it moves the object's values,
    the probe recording's tracking error at them and at the probe fit's (one uniform stiffness, as the push
    fit) is recorded. The choice goes to OUT/choice.json (chosen, fitted and prior values, errors, the
    layout) and the log. `sysid_flags`: more options of every `twinbench sysid` run (e.g. --cma.workers)."""
    from twinbench.construct._json import write_json

    probe_fit = json.loads(report.read_text())
    held = {k: v for k, v in probe_fit["global_params"].items() if not k.startswith("tool_")}
    recording, on_layout = push, {} if layout is None else layout[1]
    push = push if layout is None else layout[0]

    def sysid(data: Path, where: Path, values: dict, *flags) -> dict:
        given = {**held, **(on_layout if data == push else {}), **values}
        margin = ("--measure-mesh-margin",) if data == push else ("--mesh-margin", str(mesh_margin))
        run("sysid", "--data", data, "--out-dir", where, "--no-progress", "--no-guess", "--no-stage2",
            "--no-stage3", *margin, *flags, *sysid_flags,
            *[a for k, v in given.items() for a in (f"--initial.{k.replace('_', '-')}", str(v))])
        return json.loads((where / "sysid_report.json").read_text())

    def fit(names: tuple[str, ...]) -> dict:
        starts = {"probe": {n: float(cell[n] if n == "tool_friction" else held[n]) for n in names},
                  "cell": {n: float(cell[n]) for n in names}}
        if starts["cell"] == starts["probe"]:
            del starts["cell"]
        search = ("--cma.search", *names, "--cma.ranges", "tool_friction=0:1.5",
                  "--cma.budget", str(PUSH_BUDGET[len(names)]))
        runs = {label: sysid(push, out / push_fit_dir(names, label), start, *search)
                for label, start in starts.items()}
        best, what, values, errors = best_push_point(runs, starts)
        prior = "cell" if "cell" in starts else "probe"  # (the same values when the cell start was dropped)
        pinned = {n: constrains(runs.get(best, {}), n, False) for n in names}  # a start as it is: unmeasured
        before = tracking_errors(runs[prior])["initial"]
        return {**adopt_push_fit(values, errors, starts[prior], before, what, pinned), "start": best,
                "contact_distance_m": float(runs[prior]["config"]["mesh_margin"])}

    names = push_search(probe_fit)
    choice = fit(names)
    if len(names) > 1 and not choice["adopted"]:
        choice = {**fit(("tool_friction",)), "rejected": choice}
    moved = {k: v for k, v in choice["chosen"].items() if k != "tool_friction" and v != held[k]}
    if moved:  # what the probe recording says of them (for the record: the probe did not constrain them)
        choice["probe_errors_m"] = {
            name: tracking_errors(sysid(probe, out / f"probe-at-{name}", values, "--no-stage1"))["final"]
            for name, values in (("probe_fit", {}), ("push_fit", moved))}
    choice["layout"] = {"data": str(push), **on_layout} if layout is not None else "identified"
    write_json(out / "choice.json", choice)
    distance = f"tool contact distance {1e3 * choice['contact_distance_m']:.2f} mm (measured)"
    log(f"# {recording.name}: " + ", ".join(f"{k} {v:.3g}" for k, v in choice["chosen"].items())
        + f", {distance} ({choice['reason']})")
    return choice


def tracking_errors(report: dict) -> dict:
    """A `twinbench sysid` report's tracking errors (m) on its fitted and held-out frames, at the initial
    values and at the kept stage: {"initial" | "final": {"train_error_m", "val_error_m"}}."""
    ev = report["evaluations"]
    return {stage: {k: ev[stage][k] for k in ("train_error_m", "val_error_m")}
            for stage in ("initial", "final")}


def _better(before: dict, after: dict) -> tuple[bool, str]:
    """Whether tracking errors `after` are below `before` on every frame set both have (no held-out frames:
    the fitted ones decide), and the comparison in words (mm)."""
    known = [k for k in before if before[k] is not None and after[k] is not None]
    ok = bool(known) and all(after[k] < before[k] for k in known)
    return ok, ", ".join(f"{k.split('_')[0]} {1e3 * after[k]:.2f} against {1e3 * before[k]:.2f} mm"
                         for k in known)


def best_push_point(runs: dict[str, dict], starts: dict[str, dict]) -> tuple[str, str, dict, dict]:
    """Of push fits from several starts (`runs`: {start: `twinbench sysid` report}; `starts`: {start: {name:
    value}}, "probe" the probe fit's values), the point that tracks the push's fitted frames best: each
    fit's kept values, and each start but "probe" as it is (a fit can end tracking worse than its start: its
    search lowers Chamfer + tracking loss, not the tracked points' mean distance). Returns its label (the
    start's, "START (as started)" for a start itself), what its values are in words (for
    `adopt_push_fit`'s reason), its values ({name: value} of the starts' names) and its tracking errors (m,
    {"train_error_m", "val_error_m"})."""
    points = [(label, "fitted", {n: float(run["global_params"][n]) for n in starts[label]},
               tracking_errors(run)["final"]) for label, run in runs.items()]
    points += [(f"{label} (as started)", f"the {label} start's", dict(starts[label]),
                tracking_errors(run)["initial"]) for label, run in runs.items() if label != "probe"]
    return min(points, key=lambda p: p[3]["train_error_m"])


def adopt_push_fit(fit: dict, after: dict, prior: dict, before: dict, what: str = "fitted",
                   constrained: dict | None = None) -> dict:
    """Whether push-fitted values `fit` ({name: value}) with tracking errors `after` (m, {"train_error_m",
    "val_error_m"}, as `tracking_errors` gives) are adopted against `prior` ({name: value}, what the twin has
    otherwise) whose tracking errors are `before`: only when they are lower on the fitted frames and on the
    held-out ones (a lower loss alone is not enough: the Chamfer term can fall while the tracked points
    drift), and then only the values the push's motion constrains (`constrained`: {name: bool}, the fit's
    identifiability; None: all of them): a value it leaves open keeps the prior's (a flat fit's value is one
    draw of many, and moves with the machine's rounding). None constrained: nothing adopted. `what` names the
    values in the reason. Returns the record: chosen, fitted and prior values ({name: value}), which the
    push constrains, the errors (m) before and of the fit, whether adopted and why."""
    fit = {n: float(fit[n]) for n in prior}
    pinned = {n: True if constrained is None else bool(constrained.get(n, False)) for n in prior}
    errors = {"initial": before, "final": after}
    better, span = _better(errors["initial"], errors["final"])
    adopted = better and any(pinned.values())
    prior = {n: float(v) for n, v in prior.items()}
    said = ", ".join(f"{k} {v:.3g}" for k, v in fit.items())
    was = ", ".join(f"{v:.3g}" for v in prior.values())
    loose = [n for n in prior if not pinned[n]]
    if adopted:
        reason = f"{what} {said} adopted: it tracks the push better than {was} ({span})"
        if loose:
            at = ", ".join(f"{prior[n]:.3g}" for n in loose)
            reason += f"; {', '.join(loose)} kept at {at}: the push does not constrain them"
    elif better:
        reason = (f"{what} {said} not adopted: it tracks the push better than {was} ({span}), but the push "
                  "constrains none of them")
    else:
        reason = (f"{what} {said} not adopted: it does not track the push better than {was} on both the "
                  f"fitted and the held-out frames ({span})")
    chosen = {n: fit[n] if adopted and pinned[n] else prior[n] for n in prior}
    return {"chosen": chosen, "fitted": fit, "prior": prior, "constrained": pinned, "adopted": adopted,
            "errors_m": errors, "reason": reason}


def camera_summary(twins: Path) -> dict:
    """What `refine-cameras` did to each camera of TWINS/construction (its refine.json): residual before and
    after, how far the camera moved, the image's shift. Empty without one (a reconstruction before it)."""
    path = Path(twins) / "construction" / "cameras" / "refine.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def fit_summary(twins: Path) -> dict:
    """What the reconstruction's fits reached (study.json's "sysid"), per object of TWINS/construction: the
    fitted sysid's tracking error on its fitted and held-out frames at the initial guess and at the kept
    stage, the kept stage and its notes, what it did to its measured inputs (smoothed, particles raised onto
    the ground), the tool friction's choice where a push was fitted, and the twin's particle layout
    (`template_layout`'s record). Empty when TWINS holds no fitted sysid."""
    work = Path(twins) / "construction" / "sysid"
    layout = work.parent / "objects" / "layout.json"  # a reconstruction before it: none
    layouts = json.loads(layout.read_text()).get("fitted", {}) if layout.is_file() else {}
    summary = {}
    for path in sorted((work / "fitted").glob("*/report.json")):
        report = json.loads(path.read_text())
        record = {**tracking_errors(report), "kept": report.get("selection", {}).get("kept"),
                  "notes": report.get("notes", []), "inputs": report.get("inputs", {})}
        choice = work / "push" / path.parent.name / "choice.json"
        if choice.is_file():
            record["push"] = json.loads(choice.read_text())
        if path.parent.name in layouts:
            record["layout"] = layouts[path.parent.name]
        summary[path.parent.name] = record
    return summary


def reconstruct(evidence: Path, out: Path, variants=VARIANTS, log: Callable[[str], None] = print,
                sysid_args: tuple[str, ...] = (), workers: int = 1) -> dict[str, Path]:
    """Rebuild the workcell of EVIDENCE (made by `make_evidence`) into OUT/<variant>/ twin directories,
    through the CLI; `sysid_args` are extra `twinbench sysid` options (default: none, its defaults);
    `workers` > 1: every `twinbench sysid` scores its candidates in that many processes (`--cma.workers`,
    the same fit, sooner)."""
    from twinbench.construct._json import write_json
    from twinbench.errors import InputError
    from twinbench.gaussians.io import load_gaussians
    from twinbench.study.real import task_cell
    from twinbench.twin import load_object

    evidence, out = Path(evidence), Path(out)
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown:
        raise InputError(f"reconstruct variants: unknown {unknown}; known: {list(VARIANTS)}")
    index = json.loads((evidence / "evidence.json").read_text())
    work = out / "construction"
    work.mkdir(parents=True, exist_ok=True)

    def run(*args) -> None:  # the public CLI in its own process, as a user runs it
        argv = [str(a) for a in args]
        log("twinbench " + shlex.join(argv))
        code = subprocess.run([sys.executable, "-c", _CLI, *argv], check=False).returncode
        if code != 0:
            raise RuntimeError(f"twinbench {argv[0]} failed with exit code {code} (command above)")

    objects = index["objects"]
    colliders = index.get("colliders", [])  # the cell's fixed parts, segmented like objects (evidence boxes)
    seg, aligned, color = work / "seg", work / "aligned", work / "color"
    run("segment", evidence / index["scan"], "--boxes", evidence / index["boxes"], "--out", seg)
    run("align-robot", seg / "robot.ply", "--urdf", index["urdf"], "--out", aligned, "--also",
        seg / "background.ply", *[seg / "objects" / f"{o}.ply" for o in (*objects, *colliders)])
    parts = [aligned / "robot.ply", aligned / "aligned" / "background.ply",
             *[aligned / "aligned" / f"{o}.ply" for o in (*objects, *colliders)]]
    # the calibration corrected on the real images (every variant: it is the twin's view, not an ablation)
    run("refine-cameras", "--scan", *parts, "--calibration", evidence / index["calibration"], "--real",
        evidence / index["real_images"], "--out", work / "cameras")
    calibration = work / "cameras" / "calibration.json"
    if any(_COLOR[v] for v in variants):
        run("align-color", "--scan", *parts, "--calibration", calibration, "--real",
            evidence / index["real_images"], "--out", color)
    physics = sorted({_PHYSICS[v] for v in variants})
    pool = ("--cma.workers", str(workers)) if workers > 1 else ()
    for kind in physics:
        flags = ("--no-stage1", "--no-stage2") if kind == "initial" else ()
        for o in objects:
            run("sysid", "--data", evidence / index["motion"][o], "--out-dir", work / "sysid" / kind,
                "--no-progress", *flags, *pool, *sysid_args)
            # each object's report beside its object (the next object's run writes its own)
            shutil.copy(work / "sysid" / kind / "sysid_report.json",
                        work / "sysid" / kind / o / "report.json")

    # the task's public definition: object templates (shape, outline, goal), controller, robot conventions,
    # tool contact
    # the cell at the evidence's preset (evidence written before "preset" was recorded: its size's)
    cell = task_cell(index["task"], index["size"], preset=index.get("preset"))
    frame_dt = cell.sim.dt * cell.sim.substeps
    tool = {kind: dataclasses.asdict(cell.robot.tool_contact) for kind in physics}
    pushes = {o: index["push"][o] for o in objects if o in index.get("push", {})}
    from_push = {}  # the object values a push fit chose, per object (the fitted variants)
    contact = {}  # the fitted twins' tool contact distance, measured from the pushes (else the cell's)
    if "fitted" in physics and pushes:
        values = {"tool_friction": cell.robot.tool_contact.friction, **{k: getattr(cell.sim, k)
                                                                          for k in PUSH_SEARCH[1:]}}
        choices = {}
        for o, rel in pushes.items():  # a rigid object's push fitted on its template's layout (`push_layout`)
            fits = work / "sysid" / "push" / o
            relaid = push_layout(evidence / rel, work / "sysid" / "fitted" / o, cell.object(o), fits / "data")
            choices[o] = _push_fit(run, evidence / rel, evidence / index["motion"][o],
                                   work / "sysid" / "fitted" / o / "report.json", fits, cell.sim.mesh_margin,
                                   values, log, relaid, pool)
        tool["fitted"]["friction"] = float(np.median([c["chosen"]["tool_friction"]
                                                      for c in choices.values()]))
        from_push = {o: {k: v for k, v in c["chosen"].items() if k != "tool_friction"}
                     for o, c in choices.items()}
        contact = {"mesh_margin": float(np.median([c["contact_distance_m"] for c in choices.values()]))}
    write_json(work / "calibration.json", json.loads(calibration.read_text()))
    rest, layouts = {}, {}
    for o in objects:
        template = cell.object(o)
        scanned = load_gaussians(aligned / "aligned" / f"{o}.ply")
        rest[o] = estimate_rest_pose(scanned.means, template.gaussians.means, float(template.rest_pose[2, 3]),
                                     scanned.base_colours, template.gaussians.base_colours)
        log(f"# {o}: rest pose from the scan x={rest[o][0, 3]:.4f} y={rest[o][1, 3]:.4f} "
            f"yaw={np.degrees(np.arctan2(rest[o][1, 0], rest[o][0, 0])):.2f} deg")
        for kind in physics:
            sim = load_object(work / "sysid" / kind / o)[1]
            substeps = max(int(sim["substeps"]), cell.sim.substeps)
            over = {k: getattr(cell.sim, k) for k in _CELL_SIM}
            over.update(substeps=substeps, dt=frame_dt / substeps)
            kept = {}
            if kind == "fitted":
                over.update(contact)
                over.update(from_push.get(o, {}))
                kept = open_values(work / "sysid" / kind / o / "report.json", cell.sim, from_push.get(o, {}))
                over.update(kept)
            over = {k: (list(v) if isinstance(v, tuple) else v) for k, v in over.items()}
            layout = _place_object(work / "sysid" / kind / o, template, rest[o], over,
                                   work / "objects" / kind / o)
            layouts.setdefault(kind, {})[o] = {**layout, "cell_values": kept}
            if layout["layout"] == "template":
                log(f"# {o} ({kind}): the task's rigid shape laid at its lattice, {layout['particles']} "
                    f"particles (identified {layout['identified_particles']}), spring Y "
                    f"{layout['spring_Y']:.4g} (the {layout['spring_Y_from']}'s), total mass "
                    f"{layout['mass']:.4g}")
            if kept:
                log(f"# {o} ({kind}): the motion constrains none of {', '.join(kept)}: the task cell's "
                    + ", ".join(f"{v:.3g}" for v in kept.values()))
    write_json(work / "objects" / "layout.json", layouts)

    fixed = [_collider_entry(cell, c, aligned / "aligned" / f"{c}.ply", work, log) for c in colliders]
    twins = {}
    for v in variants:
        cmap = "color/color_map.json" if _COLOR[v] else None
        config = {
            "name": f"{index['task']}-{v}",
            "robot": robot_entry(cell.robot, cmap, tool[_PHYSICS[v]]),
            "background": {"gaussians": "aligned/aligned/background.ply", "color_map": cmap},
            "objects": [{"dir": f"objects/{_PHYSICS[v]}/{o}", "rest_pose": rest[o].tolist(),
                         "gaussians": f"aligned/aligned/{o}.ply", "color_map": cmap} for o in objects],
            "colliders": [{**c, "color_map": cmap} for c in fixed],
            "cameras": "calibration.json",
            "controller": json.loads(json.dumps(dataclasses.asdict(cell.controller))),
            "render": {"background": list(cell.render_background)},
        }
        path = work / f"build-{v}.json"
        write_json(path, config)
        run("twin", "build", path, "--out", out / v)
        twins[v] = out / v
    return twins

