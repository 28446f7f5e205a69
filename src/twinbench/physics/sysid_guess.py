"""Physically scaled starting values for system identification, computed from the observed motion alone.

    guesses = physical_guesses(data, model)   # model: the object under the initial values (its springs)

Each guess is a dict: ``value`` (None where the motion does not show the effect) and ``from`` (how it
was measured, or why not). Only the fitted frames of ``data`` (its training frames) are read.

- **stiffness** (``spring_Y``, per unit strain, as the springs use it): while the control points hold
  the object up, the control springs (each control point's shortest: within 1.5x its shortest, at most 8)
  carry the weight of the particles off the ground and their
  vertical acceleration, ``sum_k M_off (g + a_z)``; their observed strains give ``sum_k S_z`` (the
  vertical component of ``strain * direction`` summed over the control springs); the ratio of the two
  sums is the stiffness at which those springs carry that load.
- **ground friction**: the deceleration of points that slide to a stop on the ground (within 4 mm of the
  level where particles rest on it,
  faster than 5 cm/s, slowing down over 3 frames) away from every control point, as a share of g (median
  over such samples); a lower bound (``lower_bound``: springs may still pull them along), so it raises
  the start only above the initial value.
- **ground restitution**: from a bounce: the square root of the object's rebound height over its fall
  height (centroid of the tracked points, first impact at more than 0.3 m/s).

Velocities and accelerations are central differences over two frames each side (1 mm of noise at 30 Hz
gives about 0.55 m/s^2 per sample); every figure is a sum or median over many samples.

The measured kinematic inputs (control points' paths, the tool's poses) are smoothed before any simulation
(:func:`smoothed_inputs`): the simulator turns their frame-to-frame noise into forces through stiff
attachments and contacts. With the ground on, particles that the measurement's noise put below it are raised
onto it (:func:`grounded`). A push recording's tool contact distance is measured where the tool carries the
object (:func:`tool_contact_distance`, `twinbench sysid --measure-mesh-margin`).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from scipy.interpolate import make_smoothing_spline
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from .model import SpringMassModel
from .sysid_data import SysIdData, SysIdFormatError

G = 9.8
GROUND_BAND = 0.004  # a point within this height of the ground level touches it (m)
MIN_SLIDE_SPEED = 0.05  # m/s
MIN_IMPACT_SPEED = 0.3  # m/s
TIGHT = 8  # control springs per control point that the stiffness guess reads
MAX_BELOW_GROUND = 0.01
"""particles at frame 0 deeper than this below the ground plane (m) are an error of the data's frame, not
noise"""
MIN_INPUT_NOISE = 5e-5
"""a measured input path (m per axis; rad for a tool's rotation) whose estimated noise is below this is
simulated as given (a robot's own poses, a synthetic path); above it, it is smoothed (`smoothed_inputs`)"""


def _tracks(data: SysIdData) -> tuple[np.ndarray, np.ndarray]:
    """The fitted frames' tracks (K, T, 3) with NaN where a track is not motion-valid."""
    stop = data.train_frames.stop
    x = data.tracked[:stop].copy()
    x[~data.motion_valid[:stop]] = np.nan
    return x, data.masses[data.tracked_indices] if data.masses is not None else np.ones(x.shape[1])


def _ground_level(x: np.ndarray) -> float:
    """The height of the particles resting on the ground (m): the 1st percentile of every tracked height,
    within [0, 1 cm] (PhysTwin's particles rest at z = 0 or at their radius)."""
    z = x[..., 2][np.isfinite(x[..., 2])]
    return float(np.clip(np.percentile(z, 1), 0.0, 0.01)) if z.size else 0.0


def _derivatives(x: np.ndarray, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """Velocity and acceleration (K, T, 3) by central differences two frames apart (NaN at the ends)."""
    v = np.full_like(x, np.nan)
    a = np.full_like(x, np.nan)
    v[2:-2] = (x[3:-1] - x[1:-3]) * fps / 2.0
    a[2:-2] = (x[4:] - 2.0 * x[2:-2] + x[:-4]) * fps * fps / 4.0
    return v, a


def difference_noise(x: np.ndarray, order: int = 2) -> float:
    """Per-axis standard deviation of white noise on the series ``x`` (frames first, NaN ignored): the
    median squared ``order``-th difference along the frames is C(2 order, order) sigma^2 (times 0.4549, the
    median of chi-square with one degree of freedom) where the signal itself is smooth at the frame rate
    (a higher order leaves less of a fast motion in the estimate). 0 without enough samples."""
    d = np.diff(np.asarray(x, np.float64), n=order, axis=0).ravel()
    d = d[np.isfinite(d)]
    return math.sqrt(float(np.median(d * d)) / (math.comb(2 * order, order) * 0.4549)) if d.size else 0.0


def track_noise(data: SysIdData) -> float:
    """Per-axis standard deviation (m) of the tracks' noise in the fitted frames: the second differences
    (:func:`difference_noise`) of each track's offset from its nearest tracked neighbour (at rest), over
    sqrt 2. The motion two neighbours share cancels (an object that swings or rings faster than the frame
    rate resolves: a track's own differences took it for noise, up to 1.6x the truth on the held-out
    family's lifts), their independent noise adds. With one track, its own second differences. 0 without
    enough samples."""
    x = _tracks(data)[0]
    if x.shape[1] < 2:
        return difference_noise(x, 2)
    rest = data.particles[data.tracked_indices]
    nearest = cKDTree(rest).query(rest, k=2)[1][:, 1]
    return difference_noise(x - x[:, nearest], 2) / math.sqrt(2.0)


def grounded(data: SysIdData) -> tuple[SysIdData, dict]:
    """``data`` with its particles that lie below the ground plane (z < 0) at frame 0 raised onto it, and
    what was done ({"below", "of", "deepest"}: how many of how many particles, the deepest in m).

    Measured particles resting on the ground scatter around it with the measurement's noise. The ground
    contact (PhysTwin's, with time of impact) acts on a particle that reaches the plane from above: one that
    starts below it and moves down is put back onto the plane from the time of impact -z / v_z, which for
    a slow particle lies far in the past, so it is thrown sideways by its velocity times that time. On
    push-T seed 4's push recording 25 of 124 particles lay up to 1 mm below the ground; at the workcell's
    true contact values the reconstructed T tracked its push at 7.9 / 14.9 mm (fitted / held-out frames),
    raised 4.2 / 3.9 mm. Raises :class:`SysIdFormatError` where particles lie deeper than
    :data:`MAX_BELOW_GROUND`: the data's ground is not at z = 0 (or the object is not on it)."""
    z = data.particles[:, 2]
    below = z < 0.0
    report = {"below": int(below.sum()), "of": int(z.size), "deepest": float(max(-z.min(), 0.0))}
    if report["deepest"] > MAX_BELOW_GROUND:
        raise SysIdFormatError(
            f"{data.source}: field 'particles': {report['below']} of {z.size} particles lie below the ground "
            f"plane z = 0, the deepest {1e3 * report['deepest']:.1f} mm (more than measurement noise, "
            f"{1e3 * MAX_BELOW_GROUND:.0f} mm): give the data in a frame whose ground is z = 0 (z up), or "
            "fit without the ground (--no-ground)")
    if not below.any():
        return data, report
    particles = data.particles.copy()
    particles[below, 2] = 0.0
    return replace(data, particles=particles), report


def _smooth(t: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Each column of ``y`` (frames first) as a cubic smoothing spline whose smoothing is chosen by
    generalised cross-validation (scipy's ``make_smoothing_spline``), evaluated at ``t``."""
    flat = y.reshape(len(t), -1)
    out = np.stack([make_smoothing_spline(t, flat[:, j])(t) for j in range(flat.shape[1])], axis=1)
    return out.reshape(y.shape)


def smoothed_inputs(data: SysIdData) -> tuple[SysIdData, dict]:
    """``data`` with its measured kinematic inputs smoothed where they are noisy, and what was done.

    The control points' paths and the tool's translation and rotation (unit quaternions kept on one
    hemisphere, renormalised) are each taken as a measurement: where its noise (:func:`difference_noise`
    of fourth differences, pooled over the input's coordinates) is at least :data:`MIN_INPUT_NOISE`, every
    coordinate is replaced by a smoothing spline chosen by generalised cross-validation. The simulator
    moves them exactly as given, so their noise becomes jerks of the attachments and of the tool's
    contact: on the study's push-T evidence, 0.5 mm of noise on the tool's poses moves the real object's
    own simulated push 6.8 / 10.1 mm (fitted / held-out frames) from its tracks, against 1.6 / 1.6 mm with
    the exact path and 1.6 / 1.6 mm with the smoothed one. Returns (data, {input: {"noise", "smoothed",
    "rms_change"}}) with noise and change in m (rad for "tool_rotation"); inputs absent are left out."""
    n = data.num_frames
    t = np.arange(n) / data.fps
    report: dict[str, dict] = {}

    def measure(name: str, y: np.ndarray, noise: float, scale: float = 1.0) -> np.ndarray:
        done = n >= 5 and noise >= MIN_INPUT_NOISE
        out = _smooth(t, y) if done else y
        report[name] = {"noise": noise, "smoothed": bool(done),
                        "rms_change": scale * float(np.sqrt(np.mean((out - y) ** 2)))}
        return out

    changes: dict = {}
    if data.num_controls:
        changes["controls"] = measure("controls", data.controls, difference_noise(data.controls, 4))
    if data.has_tool:
        poses = data.tool_poses.copy()
        poses[:, :3, 3] = measure("tool_translation", poses[:, :3, 3], difference_noise(poses[:, :3, 3], 4))
        q = Rotation.from_matrix(poses[:, :3, :3]).as_quat()
        q[1:][np.cumsum(np.einsum("ij,ij->i", q[1:], q[:-1]) < 0) % 2 == 1] *= -1.0  # one hemisphere
        # per axis of the angle: the quaternion's noise (half the angle's, in the 3 directions tangent to
        # it) summed over its 4 components, however the rotation spreads it over them
        angle = 2.0 * math.sqrt(sum(difference_noise(q[:, j], 4) ** 2 for j in range(4)) / 3.0)
        qs = measure("tool_rotation", q, angle, 2.0)
        if report["tool_rotation"]["smoothed"]:
            poses[:, :3, :3] = Rotation.from_quat(qs / np.linalg.norm(qs, axis=1, keepdims=True)).as_matrix()
        changes["tool_poses"] = poses
    smoothed = any(r["smoothed"] for r in report.values())
    return (replace(data, **changes) if smoothed else data), report


def stiffness_guess(data: SysIdData, model: SpringMassModel) -> dict:
    if not data.num_controls:
        return {"value": None, "from": "no control points: no known load on the object"}
    x, m = _tracks(data)
    _, a = _derivatives(x, data.fps)
    n_p = model.num_particles
    sp = model.springs_np[model.num_object_springs:].astype(np.int64)
    rest = model.rest_lengths_np[model.num_object_springs:].astype(np.float64)
    part = np.where(sp[:, 0] < n_p, sp[:, 0], sp[:, 1])
    ctrl = np.where(sp[:, 0] < n_p, sp[:, 1], sp[:, 0]) - n_p
    # the springs that carry the load: each control point's shortest ones (within 1.5x its shortest, at
    # most TIGHT); the long ones also stretch with the object's own deformation
    keep = np.zeros(len(rest), bool)
    for c in np.unique(ctrl):
        idx = np.flatnonzero(ctrl == c)
        idx = idx[np.argsort(rest[idx], kind="stable")][:TIGHT]
        keep[idx[rest[idx] <= 1.5 * rest[idx[0]]]] = True
    part, ctrl, rest = part[keep], ctrl[keep], rest[keep]
    col = np.full(n_p, -1)
    col[data.tracked_indices] = np.arange(data.tracked_indices.size)
    seen = col[part] >= 0
    if not seen.any():
        return {"value": None, "from": "no tracked particle is attached to a control point"}
    mass_total = float(np.sum(data.masses)) if data.masses is not None else float(n_p)
    ground = _ground_level(x)
    var = track_noise(data) ** 2  # per-axis noise variance
    force, strain, frames = 0.0, 0.0, 0
    for k in range(2, x.shape[0] - 2):
        ok = np.all(np.isfinite(x[k]), axis=1)
        if ok.sum() < 3:
            continue
        off = ok & (x[k, :, 2] > ground + GROUND_BAND)
        m_off = mass_total * float(m[off].sum() / m[ok].sum())
        acc = a[k, off, 2]
        acc = acc[np.isfinite(acc)]
        if m_off < 0.2 * mass_total or acc.size < 3:
            continue
        s = seen & ok[np.maximum(col[part], 0)]
        if not s.any():
            continue
        d = data.controls[k][ctrl[s]] - x[k, col[part[s]]]
        length = np.linalg.norm(d, axis=1)
        length = np.sqrt(np.maximum(length * length - 2.0 * var, 0.0))  # noise lengthens on average
        s_z = float(np.sum((length / rest[s] - 1.0) * d[:, 2] / np.maximum(length, 1e-9)))
        s_z *= seen.sum() / s.sum()  # the attached particles not tracked in this frame
        if s_z <= 0:
            continue
        force += m_off * (G + float(np.mean(acc)))
        strain += s_z
        frames += 1
    if frames < 3 or force <= 0:
        return {"value": None, "from": f"the control points hold the object up in {frames} fitted frame(s) "
                                        "(need 3): no load to scale the stiffness by"}
    return {"value": force / strain, "frames": frames,
            "from": f"weight + vertical inertia of the particles off the ground over the control springs' "
                    f"vertical strain, {frames} frames"}


def friction_guess(data: SysIdData, control_radius: float) -> dict:
    x, _ = _tracks(data)
    v, a = _derivatives(x, data.fps)
    near = np.zeros(x.shape[:2], bool)
    if data.num_controls:
        c = data.controls[: x.shape[0]]
        dist = np.linalg.norm(x[:, :, None, :] - c[:, None, :, :], axis=3)
        near = np.any(dist < 1.5 * control_radius, axis=2)
    speed = np.linalg.norm(v[..., :2], axis=2)
    low = x[..., 2] < _ground_level(x) + GROUND_BAND
    use = low & ~near & (speed > MIN_SLIDE_SPEED) & np.isfinite(a[..., 0])
    use[2:-2] &= low[1:-3] & low[3:-1] & (speed[1:-3] > speed[2:-2]) & (speed[2:-2] > speed[3:-1])
    if use.sum() < 5:
        return {"value": None, "from": f"{int(use.sum())} samples of points sliding on the ground away from "
                                       "the control points (need 5)"}
    decel = -np.sum(a[use][:, :2] * v[use][:, :2], axis=1) / speed[use]
    return {"value": float(np.median(decel)) / G, "samples": int(use.sum()), "lower_bound": True,
            "from": f"median deceleration of {int(use.sum())} samples of points sliding to a stop, over g (a "
                    "lower bound: springs may pull them along)"}


def restitution_guess(data: SysIdData) -> dict:
    x, _ = _tracks(data)
    zc = np.array([np.nanmean(f[:, 2]) if np.isfinite(f[:, 2]).any() else np.nan for f in x])
    zlow = np.array([np.nanmin(f[:, 2]) if np.isfinite(f[:, 2]).any() else np.nan for f in x])
    vz = np.gradient(zc) * data.fps
    ground = _ground_level(x)
    for k in range(1, len(zc) - 2):
        if zlow[k] < ground + GROUND_BAND and vz[k - 1] < -MIN_IMPACT_SPEED:
            top = float(np.nanmax(zc[: k + 1]))
            bottom = float(np.nanmin(zc[k: k + 3]))
            after = zc[k + 1:]
            rise = np.flatnonzero(np.diff(after) < 0)  # the apex: the first frame the centroid falls again
            apex = float(np.nanmax(after[: rise[0] + 1])) if rise.size else float(np.nanmax(after))
            if top - bottom < 0.005 or not rise.size:
                break
            e = math.sqrt(min(max(apex - bottom, 0.0) / (top - bottom), 1.0))
            return {"value": min(max(e, 0.02), 0.98), "frame": k,
                    "from": f"rebound {1e3 * (apex - bottom):.1f} mm over fall {1e3 * (top - bottom):.1f} mm "
                            f"(impact at frame {k})"}
    return {"value": None, "from": f"no impact faster than {MIN_IMPACT_SPEED} m/s followed by a rebound in "
                                   "the fitted frames"}


def physical_guesses(data: SysIdData, model: SpringMassModel, control_radius: float) -> dict[str, dict]:
    """Guesses for ``spring_Y`` and, with the ground on, ``ground_friction`` and ``ground_restitution``
    (see the module docstring); ``data`` should be the fitted view (its training frames are read)."""
    out = {"spring_Y": stiffness_guess(data, model)}
    if model.params.ground:
        out["ground_friction"] = friction_guess(data, control_radius)
        out["ground_restitution"] = restitution_guess(data)
    return out


CARRY_REACH = 0.03  # m: tracked points this near the tool are the ones it would carry
CARRY_SHARE = 0.5  # a frame is a push when those points move along the tool's motion by this share of it
CARRY_MIN_STEP = 0.002  # m: the tool's least motion over a frame for that frame to count (tracks' noise)


def tool_contact_distance(data: SysIdData, reach: float = CARRY_REACH, share: float = CARRY_SHARE,
                          min_step: float = CARRY_MIN_STEP) -> tuple[float, np.ndarray]:
    """The distance a tool keeps from the object's points while it pushes it, measured on a recording with a
    tool (``tool_*``): in each frame where the tool carries the object (its path, smoothed as sysid smooths
    it, moves at least `min_step`, and the tracked points within `reach` of it move along its motion by at
    least `share` of it), the nearest visible observed point's distance to the tool's mesh; the median over
    those frames. This is the contact distance (`SimParams.mesh_margin`) at which particles placed on the
    observed points meet the tool where the real object does. The nearest of several noisy points sits
    nearer than the surface they sample, so the figure runs low, by up to about the points' noise. Returns
    (distance in m, the frames used).

    Raises ValueError naming the recording when it has no tool, or fewer than 3 frames where the tool
    carries the object (then give the distance yourself: `twinbench sysid --mesh-margin`)."""
    import trimesh

    if not data.has_tool:
        raise ValueError(f"{data.source}: no tool in this recording (tool_vertices, tool_faces, tool_poses); "
                         "a contact distance is measured on a push recording")
    tool = smoothed_inputs(data)[0].tool_path()  # the tool's pose noise would pass for motion
    centre = tool.mean(axis=1)
    meshes: dict[int, trimesh.Trimesh] = {}

    def distance(k: int, points: np.ndarray) -> np.ndarray:  # to the tool's mesh in frame k (built once)
        if k not in meshes:
            meshes[k] = trimesh.Trimesh(tool[k], data.tool_faces, process=False)
        return trimesh.proximity.closest_point(meshes[k], points)[1]

    used, gaps = [], []
    for k in range(1, data.num_frames):
        step = centre[k] - centre[k - 1]
        length = float(np.linalg.norm(step))
        if length < min_step:
            continue
        ok = data.motion_valid[k - 1] & data.motion_valid[k]
        before = data.tracked[k - 1][ok]
        near = distance(k - 1, before) < reach
        seen = data.observed[k][data.visibility[k]]
        if (not near.any() or not len(seen)
                or np.mean((data.tracked[k][ok][near] - before[near]) @ step) < share * length ** 2):
            continue
        used.append(k)
        gaps.append(float(distance(k, seen).min()))
    if len(used) < 3:
        raise ValueError(f"{data.source}: the tool carries the object in {len(used)} frame(s) of this "
                         "recording (need 3: frames where the tool moves and the tracked points beside it "
                         "move with it); no contact distance can be measured from it: give one (twinbench "
                         "sysid --mesh-margin)")
    return float(np.median(gaps)), np.asarray(used)
