"""The input of system identification: observed motion of one object (:class:`SysIdData`).

Files holding it (a sysid directory: ``sysid.json`` + ``data.npz`` with the arrays below under their
field names; a PhysTwin case's ``final_data.pkl``) are read by ``twinbench.construct.sysid_io``.

World frame = robot base frame, z up, ground plane z = 0, SI units (DESIGN section 3). Frame 0 is
the initial state; simulated frame ``k >= 1`` moves the control points from ``controls[k-1]`` to
``controls[k]`` and is compared with the observations of frame ``k``. The last
``validation_frames`` frames are held out (never used for fitting).

Arrays (F frames, P particles, N observed points, T tracked points, K control points):

=================== ============ ==================================================================
key                 shape        meaning
=================== ============ ==================================================================
``particles``       (P, 3)       initial particle positions (observed surface points plus optional
                                 surface / interior completions), at rest at frame 0
``observed``        (F, N, 3)    observed 3D points per frame (e.g. from depth), finite everywhere
                                 (invisible entries may hold any finite value, e.g. 0)
``visibility``      (F, N) bool  which observed points exist in each frame (one-sided Chamfer)
``tracked_indices`` (T,) int     particle index of each tracked point (unique)
``tracked``         (F, T, 3)    observed positions of the tracked points
``motion_valid``    (F, T) bool  whether each track is trustworthy in each frame (tracking loss)
``controls``        (F, K, 3)    kinematic control-point trajectories (e.g. hand keypoints); K may be 0
``springs``         (M, 2) int   optional explicit object springs (otherwise the radius rule)
``rest_lengths``    (M,)         optional, with ``springs`` (default: distances in ``particles``)
``masses``          (P,)         optional per-particle masses (default 1, as PhysTwin)
``surface_indices`` (S,) int     optional particles the Chamfer term may match (default: all;
                                 PhysTwin excludes interior completions)
``tool_vertices``   (V, 3)       optional kinematic tool that touches the object (pusher, finger): its
                                 triangle mesh's vertices in the tool's own frame
``tool_faces``      (C, 3) int   with ``tool_vertices``: the mesh's triangles
``tool_poses``      (F, 4, 4)    with ``tool_vertices``: world-from-tool rigid transform per frame
=================== ============ ==================================================================

The tool moves from ``tool_poses[k-1]`` to ``tool_poses[k]`` in frame k (its vertices linearly
interpolated over the substeps) and acts on the object by contact only, with its own friction and
restitution (``GlobalParams.tool_friction``, ``tool_restitution``): pushes, not grips.

Every array is validated on construction; errors name the file and field (:class:`SysIdFormatError`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from twinbench.errors import InputError
from twinbench.transforms import transform_points

MIN_SPRING_LENGTH = 1e-4  # as the builder's radius rule: shorter springs make a 0/0 strain
REQUIRED_ARRAYS = ("particles", "observed", "visibility", "tracked_indices", "tracked", "motion_valid",
                   "controls")
OPTIONAL_ARRAYS = ("springs", "rest_lengths", "masses", "surface_indices", "tool_vertices", "tool_faces",
                   "tool_poses")
TOOL_ARRAYS = ("tool_vertices", "tool_faces", "tool_poses")


class SysIdFormatError(InputError):
    """Bad system-identification input; the message names the file, the field and the fix."""


def _err(source: str, key: str, msg: str) -> SysIdFormatError:
    return SysIdFormatError(f"{source}: field '{key}' {msg}")


def _float_array(source: str, key: str, value, shape: tuple) -> np.ndarray:
    """Float64 array of ``shape`` (None entries are free), finite everywhere."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise _err(source, key, f"must be a numeric array ({exc})") from None
    _check_shape(source, key, arr, shape)
    if not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0].tolist()
        raise _err(source, key, f"contains NaN or inf (first at index {bad}); give finite values "
                                "(mark missing observations with the visibility / motion_valid masks)")
    return arr


def _check_shape(source: str, key: str, arr: np.ndarray, shape: tuple) -> None:
    want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
    if arr.ndim != len(shape) or any(s is not None and a != s for a, s in zip(arr.shape, shape, strict=True)):
        raise _err(source, key, f"has shape {arr.shape}, expected {want}")


def _bool_array(source: str, key: str, value, shape: tuple) -> np.ndarray:
    arr = np.asarray(value)
    _check_shape(source, key, arr, shape)
    if arr.dtype != np.bool_:
        if not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)) \
                or not np.all(np.isin(arr, (0, 1))):
            raise _err(source, key, "must be boolean (or 0/1)")
        arr = arr.astype(bool)
    return arr


def _index_array(source: str, key: str, value, shape: tuple, upper: int, what: str) -> np.ndarray:
    arr = np.asarray(value)
    _check_shape(source, key, arr, shape)
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise _err(source, key, f"must hold integer {what} indices, got dtype {arr.dtype}")
    arr = arr.astype(np.int64)
    if arr.size and (arr.min() < 0 or arr.max() >= upper):
        raise _err(source, key, f"indexes {what} outside [0, {upper})")
    return arr


@dataclass(frozen=True, eq=False)
class SysIdData:
    """Observed motion of one object (see the module docstring for every field's meaning).

    Construction validates and normalises every array (float64 positions, bool masks, int64
    indices); ``source`` names the file in error messages.
    """

    particles: np.ndarray
    observed: np.ndarray
    visibility: np.ndarray
    tracked_indices: np.ndarray
    tracked: np.ndarray
    motion_valid: np.ndarray
    controls: np.ndarray
    fps: float = 30.0
    validation_frames: int = 0
    name: str = "object"
    springs: np.ndarray | None = None
    rest_lengths: np.ndarray | None = None
    masses: np.ndarray | None = None
    surface_indices: np.ndarray | None = None
    tool_vertices: np.ndarray | None = None
    tool_faces: np.ndarray | None = None
    tool_poses: np.ndarray | None = None
    source: str = field(default="<memory>", compare=False)

    def __post_init__(self) -> None:
        src = self.source
        s = object.__setattr__
        p = _float_array(src, "particles", self.particles, (None, 3))
        if p.shape[0] == 0:
            raise _err(src, "particles", "is empty; give at least one particle")
        n_p = p.shape[0]
        s(self, "particles", p)
        obs = _float_array(src, "observed", self.observed, (None, None, 3))
        n_f = obs.shape[0]
        if n_f < 2:
            raise _err(src, "observed", f"has {n_f} frame(s); give the initial frame and at least one more")
        s(self, "observed", obs)
        vis = _bool_array(src, "visibility", self.visibility, (n_f, obs.shape[1]))
        s(self, "visibility", vis)
        empty = np.flatnonzero(~vis[1:].any(axis=1)) + 1
        if empty.size:
            raise _err(src, "visibility", f"frame(s) {empty[:10].tolist()} have no visible observed points; "
                                          "drop those frames or mark the points that were seen")
        ti = _index_array(src, "tracked_indices", self.tracked_indices, (None,), n_p, "particle")
        if ti.size == 0:
            raise _err(src, "tracked_indices", "is empty; give at least one tracked particle")
        if np.unique(ti).size != ti.size:
            raise _err(src, "tracked_indices", "repeats particle indices; give each track its own particle")
        s(self, "tracked_indices", ti)
        s(self, "tracked", _float_array(src, "tracked", self.tracked, (n_f, ti.size, 3)))
        s(self, "motion_valid", _bool_array(src, "motion_valid", self.motion_valid, (n_f, ti.size)))
        ctl = _float_array(src, "controls", self.controls, (n_f, None, 3))
        s(self, "controls", ctl)
        if ctl.shape[1]:
            d = np.linalg.norm(ctl[0][:, None, :] - p[None, :, :], axis=2)
            c, j = np.unravel_index(np.argmin(d), d.shape)
            if d[c, j] <= MIN_SPRING_LENGTH:
                raise _err(src, "controls", f"point {c} at frame 0 coincides with particle {j} (a zero-"
                                            "length control spring); offset the control point")
        fps = float(self.fps)
        if not (math.isfinite(fps) and fps > 0):
            raise _err(src, "fps", f"must be a positive number, got {self.fps!r}")
        s(self, "fps", fps)
        v = self.validation_frames
        if isinstance(v, bool) or int(v) != v or not 0 <= v <= n_f - 2:
            raise _err(src, "validation_frames", f"must be an integer in [0, {n_f - 2}] (keep at least one "
                                                 f"training frame after frame 0), got {v!r}")
        s(self, "validation_frames", int(v))
        if not isinstance(self.name, str) or not self.name or "/" in self.name or "\\" in self.name:
            raise _err(src, "name", f"must be a non-empty string without path separators, got {self.name!r}")
        self._check_springs(p)
        if self.masses is not None:
            m = _float_array(src, "masses", self.masses, (n_p,))
            if np.any(m <= 0):
                raise _err(src, "masses", "must be > 0 (particle masses)")
            s(self, "masses", m)
        if self.surface_indices is not None:
            si = _index_array(src, "surface_indices", self.surface_indices, (None,), n_p, "particle")
            if si.size == 0:
                raise _err(src, "surface_indices", "is empty; omit it to match all particles")
            s(self, "surface_indices", np.unique(si))
        self._check_tool(n_f)

    def _check_tool(self, n_f: int) -> None:
        src = self.source
        given = [k for k in TOOL_ARRAYS if getattr(self, k) is not None]
        if not given:
            return
        if len(given) < len(TOOL_ARRAYS):
            missing = [k for k in TOOL_ARRAYS if k not in given]
            raise _err(src, missing[0], f"is missing while {', '.join(given)} is given; a tool needs "
                                        f"{', '.join(TOOL_ARRAYS)} (or none of them)")
        verts = _float_array(src, "tool_vertices", self.tool_vertices, (None, 3))
        if verts.shape[0] < 3:
            raise _err(src, "tool_vertices", f"has {verts.shape[0]} vertices; a mesh needs at least 3")
        faces = _index_array(src, "tool_faces", self.tool_faces, (None, 3), verts.shape[0], "vertex")
        if faces.shape[0] == 0:
            raise _err(src, "tool_faces", "is empty; give the tool mesh's triangles")
        poses = _float_array(src, "tool_poses", self.tool_poses, (n_f, 4, 4))
        rot = poses[:, :3, :3]
        bad = np.flatnonzero(
            (np.abs(rot @ rot.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2)) > 1e-4)
            | (np.linalg.det(rot) < 0) | (np.abs(poses[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1) > 1e-9)
        )
        if bad.size:
            raise _err(src, "tool_poses", f"frame {bad[0]} is not a rigid transform (rotation block "
                                          "orthonormal with det +1, last row 0 0 0 1)")
        s = object.__setattr__
        s(self, "tool_vertices", verts)
        s(self, "tool_faces", faces.astype(np.int32))
        s(self, "tool_poses", poses)

    def _check_springs(self, p: np.ndarray) -> None:
        src = self.source
        if self.springs is None:
            if self.rest_lengths is not None:
                raise _err(src, "rest_lengths", "is given without 'springs'; give both or neither")
            return
        sp = _index_array(src, "springs", self.springs, (None, 2), p.shape[0], "particle")
        if sp.shape[0] == 0:
            raise _err(src, "springs", "is empty; omit it to build springs by the radius rule")
        loops = np.flatnonzero(sp[:, 0] == sp[:, 1])
        if loops.size:
            raise _err(src, "springs", f"spring {loops[0]} joins particle {sp[loops[0], 0]} to itself")
        if self.rest_lengths is None:
            rest = np.linalg.norm(p[sp[:, 1]] - p[sp[:, 0]], axis=1)
            short = np.flatnonzero(rest <= MIN_SPRING_LENGTH)
            if short.size:
                i = short[0]
                raise _err(src, "springs", f"spring {i} ({sp[i, 0]}, {sp[i, 1]}) has zero length "
                                           f"({rest[i]:.2e} m <= {MIN_SPRING_LENGTH}); remove it or merge "
                                           "the coincident particles")
        else:
            rest = _float_array(src, "rest_lengths", self.rest_lengths, (sp.shape[0],))
            short = np.flatnonzero(rest <= MIN_SPRING_LENGTH)
            if short.size:
                raise _err(src, "rest_lengths", f"spring {short[0]} has rest length {rest[short[0]]:.2e} m "
                                                f"(<= {MIN_SPRING_LENGTH}): zero-length springs make a 0/0 "
                                                "strain")
        object.__setattr__(self, "springs", sp.astype(np.int32))
        object.__setattr__(self, "rest_lengths", rest)

    def arrays(self) -> dict[str, np.ndarray]:
        """The arrays (required ones and the optional ones given) under their field names, as a sysid
        directory's ``.npz`` holds them."""
        names = REQUIRED_ARRAYS + OPTIONAL_ARRAYS
        return {k: getattr(self, k) for k in names if getattr(self, k) is not None}

    # ------------------------------------------------------------------ derived sizes
    @property
    def num_frames(self) -> int:
        return int(self.observed.shape[0])

    @property
    def num_particles(self) -> int:
        return int(self.particles.shape[0])

    @property
    def num_controls(self) -> int:
        return int(self.controls.shape[1])

    @property
    def has_tool(self) -> bool:
        return self.tool_vertices is not None

    def tool_path(self) -> np.ndarray | None:
        """The tool's vertices in the world frame per frame, (F, V, 3); None without a tool."""
        if self.tool_vertices is None:
            return None
        return transform_points(self.tool_poses, self.tool_vertices)

    @property
    def train_frames(self) -> range:
        """Simulated frames used for fitting: 1 .. F - 1 - validation_frames."""
        return range(1, self.num_frames - self.validation_frames)

    @property
    def val_frames(self) -> range:
        return range(self.num_frames - self.validation_frames, self.num_frames)


MASS_FLOOR = 0.3  # lightest particle mass by observed share, relative to the mean (a light particle needs a
# shorter time step: the stable step scales with the square root of the lightest mass)
POINTS_PER_PARTICLE = 8  # observed points a particle collects on average when masses go by observed share


def observed_masses(data: SysIdData, floor: float = MASS_FLOOR,
                    per_particle: int = POINTS_PER_PARTICLE) -> np.ndarray:
    """Per-particle masses (mean 1: PhysTwin's unit scale, the same total) in proportion to the part of the
    observed object each particle stands for: every point visible in frame 0 is shared equally by its k
    nearest particles, k such that a particle collects about `per_particle` points on average; shares under
    `floor` times the mean are lifted to it before every mass is scaled to the total (so the lightest ends
    a little under `floor` where the floor binds).

    Unit masses put the centre of mass where the particles crowd: a 1.5 cm voxel pick of a 1 cm lattice
    (the study's push-T) moves it about 1 cm. The observed points must sample the object as its particles
    do: data with interior completions (``surface_indices``: observed points on the surface only) raise
    ValueError, as do fewer observed points than a quarter of the particles."""
    from scipy.spatial import cKDTree

    if data.surface_indices is not None:
        raise ValueError(f"{data.source}: masses by observed share need observed points that sample the "
                         "whole object; this data's particles include interior completions (surface_indices):"
                         " give masses in the data (field 'masses') or keep them as given (--masses data)")
    points = data.observed[0][data.visibility[0]]
    n = data.num_particles
    if 4 * len(points) < n:
        raise ValueError(f"{data.source}: masses by observed share: {len(points)} observed points visible "
                         f"in frame 0 for {n} particles (need at least a quarter as many); give masses in "
                         "the data (field 'masses') or keep them as given (--masses data)")
    k = int(min(max(math.ceil(per_particle * n / len(points)), 1), n))
    nearest = cKDTree(data.particles).query(points, k=k)[1].reshape(len(points), k)
    share = np.bincount(nearest.ravel(), minlength=n).astype(np.float64)
    mass = np.maximum(share / share.mean(), floor)
    return mass * (n / mass.sum())
