"""Spring-mass data objects (model / state / control) and the builder that makes a model."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import warp as wp
from scipy.spatial import cKDTree

from twinbench.errors import InputError

from .params import SimParams

RADIUS_SLACK = 1e-6  # inclusive radius with relative slack (golden README)
TIE_DECIMALS = 9  # distances equal after rounding to 1e-9 m are ties, broken by lower index
MIN_REST_LENGTH = 1e-4


def check_device(device: str, field: str = "device") -> str:
    """`device` if Warp can run on it ("cpu", "cuda" or "cuda:N"), else InputError naming `field` and the fix:
    a machine without an NVIDIA driver or GPU, or fewer GPUs than N (Warp's own error there is a RuntimeError
    from inside a launch)."""
    name = str(device)
    head, sep, index = name.partition(":")
    if name == "cpu":
        return name
    if head != "cuda" or (sep and not index.isdigit()):
        raise InputError(f"{field} {name!r}: expected 'cpu', 'cuda' or 'cuda:N'")
    wp.init()
    count = wp.get_cuda_device_count()
    if count == 0:
        raise InputError(f"{field} {name!r}: Warp finds no CUDA device on this machine (no NVIDIA GPU or "
                         "driver); use 'cpu' (every path runs there)")
    if sep and int(index) >= count:
        raise InputError(f"{field} {name!r}: this machine has {count} CUDA device(s), cuda:0 to "
                         f"cuda:{count - 1}")
    return name


# ----------------------------------------------------------------------------------------------
# input validation helpers


def _points(name: str, points, *, allow_empty: bool = False) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {arr.shape}")
    if arr.shape[0] == 0 and not allow_empty:
        raise ValueError(f"{name} is empty; pass at least one point")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinite values; pass finite coordinates")
    return arr


def _positive(name: str, value: float) -> float:
    value = float(value)
    if not (value > 0 and np.isfinite(value)):
        raise ValueError(f"{name} must be a positive finite number, got {value}")
    return value


def _count(name: str, value: int) -> int:
    if int(value) != value or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def _per_item(name: str, value, n: int, *, positive: bool) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,):
        raise ValueError(f"{name} must be a scalar or have shape ({n},), got {arr.shape}")
    if not np.all(np.isfinite(arr)) or (positive and np.any(arr <= 0)):
        raise ValueError(f"{name} must be finite{' and > 0' if positive else ''}")
    return arr


def _restitution_friction(restitution: float, friction: float) -> tuple[float, float]:
    if not 0.0 <= restitution <= 1.0:
        raise ValueError(f"restitution must be in [0, 1], got {restitution}")
    if not 0.0 <= friction <= 2.0:
        raise ValueError(f"friction must be in [0, 2], got {friction}")
    return float(restitution), float(friction)


def _sorted_neighbours(tree: cKDTree, points: np.ndarray, query: np.ndarray, radius: float,
                       max_neighbors: int, exclude_self: bool) -> list[np.ndarray]:
    """Per query point: indices within ``radius`` (inclusive, 1e-6 relative slack), nearest first,
    ties (distances equal at 1e-9 m) to the lower index, at most ``max_neighbors``."""
    out = []
    for qi, cand in enumerate(tree.query_ball_point(query, radius * (1.0 + RADIUS_SLACK))):
        cand = np.asarray(cand, dtype=np.int64)
        if exclude_self:
            cand = cand[cand != qi]
        d = np.round(np.linalg.norm(points[cand] - query[qi], axis=1), TIE_DECIMALS)
        order = np.lexsort((cand, d))
        out.append(cand[order][:max_neighbors])
    return out


def radius_springs(points, radius: float = 0.02, max_neighbors: int = 30) -> np.ndarray:
    """PhysTwin's object-spring rule (golden README): visit particles in index order, take up to
    ``max_neighbors`` others within ``radius`` nearest first, keep each unordered pair once if its rest
    length is > 1e-4. Returns (M, 2) int32 pairs [i, j] in creation order."""
    pts = _points("points", points)
    radius = _positive("radius", radius)
    max_neighbors = _count("max_neighbors", max_neighbors)
    tree = cKDTree(pts)
    seen: set[tuple[int, int]] = set()
    pairs: list[tuple[int, int]] = []
    for i, nbrs in enumerate(_sorted_neighbours(tree, pts, pts, radius, max_neighbors, exclude_self=True)):
        for j in nbrs.tolist():
            key = (i, j) if i < j else (j, i)
            if key in seen or np.linalg.norm(pts[i] - pts[j]) <= MIN_REST_LENGTH:
                continue
            seen.add(key)
            pairs.append((i, j))
    return np.asarray(pairs, dtype=np.int32).reshape(-1, 2)


def lattice(nx: int, ny: int, nz: int, spacing: float = 0.01, origin=(0.0, 0.0, 0.0)) -> np.ndarray:
    """(nx * ny * nz, 3) float64 points of a regular lattice (x slowest, z fastest, as in the golden
    files), starting at ``origin``: a ready-made body for tests, demos and benchmarks."""
    g = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1).reshape(-1, 3)
    return g * spacing + np.asarray(origin, dtype=np.float64)


def _rest_lengths(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(b.astype(np.float64) - a.astype(np.float64), axis=1).astype(np.float32)


# ----------------------------------------------------------------------------------------------
# data objects


@dataclass
class State:
    """Particle positions ``x`` and velocities ``v`` (wp.array of vec3, length = model.num_particles)."""

    x: wp.array
    v: wp.array

    def assign(self, other: State) -> None:
        """Copy ``other`` into this state (no allocation)."""
        wp.copy(self.x, other.x)
        wp.copy(self.v, other.v)

    def numpy(self) -> tuple[np.ndarray, np.ndarray]:
        return self.x.numpy(), self.v.numpy()


@dataclass
class Control:
    """Kinematic inputs of one frame: control-point targets and kinematic-mesh vertex targets.

    ``ctrl_from``/``ctrl_to`` are the control positions at the frame start / end (linearly
    interpolated over the substeps, zero velocity); ``kin_from``/``kin_to`` hold the same for the vertices
    of every kinematic mesh, and ``mesh_from``/``mesh_to`` are their per-mesh views (keyed by mesh id).
    """

    ctrl_from: wp.array
    ctrl_to: wp.array
    kin_from: wp.array | None = None
    kin_to: wp.array | None = None
    mesh_from: dict[int, wp.array] = field(default_factory=dict)
    mesh_to: dict[int, wp.array] = field(default_factory=dict)
    mesh_version: int = 0

    def set_control_points(self, frm, to) -> None:
        """Set this frame's control-point positions at the start (``frm``) and end (``to``)."""
        k = self.ctrl_from.shape[0]
        for name, val in (("frm", frm), ("to", to)):
            arr = _points(name, val, allow_empty=True)
            if arr.shape[0] != k:
                raise ValueError(f"{name} must have shape ({k}, 3) (one row per control point), "
                                 f"got {arr.shape}")
        self.ctrl_from.assign(np.asarray(frm, dtype=np.float32))
        self.ctrl_to.assign(np.asarray(to, dtype=np.float32))

    def set_kinematic_mesh(self, mesh_id: int, vertices_from, vertices_to) -> None:
        """Set a kinematic mesh's vertex positions at the frame start and end."""
        if mesh_id not in self.mesh_from:
            raise ValueError(f"mesh_id={mesh_id} is not a kinematic mesh of this model "
                             f"(kinematic ids: {sorted(self.mesh_from)})")
        nv = self.mesh_from[mesh_id].shape[0]
        for name, val in (("vertices_from", vertices_from), ("vertices_to", vertices_to)):
            arr = _points(name, val)
            if arr.shape[0] != nv:
                raise ValueError(f"{name} must have shape ({nv}, 3) like the mesh, got {arr.shape}")
        self.mesh_from[mesh_id].assign(np.asarray(vertices_from, dtype=np.float32))
        self.mesh_to[mesh_id].assign(np.asarray(vertices_to, dtype=np.float32))
        self.mesh_version += 1


@dataclass
class MeshInfo:
    """One triangle mesh collider (static or kinematic)."""

    mesh: wp.Mesh
    faces: np.ndarray
    vertices: np.ndarray
    restitution: float
    friction: float
    kinematic: bool
    face_offset: int
    vertex_offset: int = -1  # kinematic meshes: first vertex in the model's `kin_points` (else -1)


@dataclass
class SpringMassModel:
    """Immutable-topology spring-mass system; ``log_y`` (per spring) is the trainable parameter.

    Springs are stored PhysTwin-style: ``springs[s] = (i, j)`` with an index ``>= num_particles``
    meaning control point ``index - num_particles``; object springs come first.
    """

    params: SimParams
    device: str
    num_particles: int
    num_control_points: int
    num_object_springs: int
    springs_np: np.ndarray
    rest_lengths_np: np.ndarray
    log_y_np: np.ndarray
    masses_np: np.ndarray
    body_id_np: np.ndarray
    x0_np: np.ndarray
    v0_np: np.ndarray
    control_x0_np: np.ndarray
    springs: wp.array
    rest_lengths: wp.array
    log_y: wp.array
    masses: wp.array
    masks: wp.array
    inc_offsets: wp.array
    inc_springs: wp.array
    nbr_offsets: wp.array
    nbr: wp.array
    meshes: list[MeshInfo]
    requires_grad: bool = False
    num_worlds: int = 1
    kin_points: wp.array | None = None  # every kinematic mesh's vertices (each mesh holds a view)
    kin_velocities: wp.array | None = None
    particle_world: wp.array | None = None  # world of each particle
    world_mesh_start: wp.array | None = None  # meshes of world w: [start[w], start[w + 1])
    # ground restitution, ground friction, object restitution, object friction (from params; trainable
    # like log_y: the kernels read them from here)
    contact_coeffs: wp.array | None = None

    @property
    def particles_per_world(self) -> int:
        return self.num_particles // self.num_worlds

    @property
    def meshes_per_world(self) -> int:
        return len(self.meshes) // self.num_worlds

    @property
    def control_points_per_world(self) -> int:
        return self.num_control_points // self.num_worlds

    @property
    def num_springs(self) -> int:
        return int(self.springs_np.shape[0])

    @property
    def num_bodies(self) -> int:
        return int(self.body_id_np.max()) + 1 if self.num_particles else 0

    @property
    def particle_collisions(self) -> bool:
        """Whether the particle-particle contact stage runs (self-collision or several bodies)."""
        p = self.params
        return bool(p.self_collision or (p.object_collision and self.num_bodies > 1))

    def state(self, requires_grad: bool | None = None) -> State:
        """A new state at the builder's initial positions and velocities."""
        rg = self.requires_grad if requires_grad is None else requires_grad
        return State(
            x=wp.array(self.x0_np, dtype=wp.vec3, device=self.device, requires_grad=rg),
            v=wp.array(self.v0_np, dtype=wp.vec3, device=self.device, requires_grad=rg),
        )

    def control(self) -> Control:
        """A new control with every target at its initial position (no motion)."""
        c0 = self.control_x0_np
        kin = [info for info in self.meshes if info.kinematic]
        k0 = np.concatenate([info.vertices for info in kin]) if kin else np.zeros((0, 3), np.float32)
        ctl = Control(
            ctrl_from=wp.array(c0, dtype=wp.vec3, device=self.device),
            ctrl_to=wp.array(c0, dtype=wp.vec3, device=self.device),
            kin_from=wp.array(k0, dtype=wp.vec3, device=self.device),
            kin_to=wp.array(k0, dtype=wp.vec3, device=self.device),
        )
        for mid, info in enumerate(self.meshes):
            if info.kinematic:
                span = slice(info.vertex_offset, info.vertex_offset + info.vertices.shape[0])
                ctl.mesh_from[mid] = ctl.kin_from[span]
                ctl.mesh_to[mid] = ctl.kin_to[span]
        return ctl

    def set_contact_coeffs(self, coeffs) -> None:
        """Overwrite (ground restitution, ground friction, object restitution, object friction), in the
        kernels' array (existing solvers and captured frames read it) and in ``params``."""
        arr = np.asarray(coeffs, dtype=np.float32)
        if arr.shape != (4,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"contact coefficients must be 4 finite values, got {arr}")
        self.contact_coeffs.assign(arr)
        names = ("ground_restitution", "ground_friction", "object_restitution", "object_friction")
        self.params = replace(self.params, **{k: float(v) for k, v in zip(names, arr, strict=True)})

    def set_spring_log_y(self, log_y) -> None:
        """Overwrite the per-spring float32 log stiffness (e.g. after system identification)."""
        arr = np.asarray(log_y, dtype=np.float32)
        if arr.shape != (self.num_springs,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"log_y must be finite with shape ({self.num_springs},), got {arr.shape}")
        self.log_y_np = arr
        self.log_y.assign(arr)


def device_meshes(specs: list, device) -> tuple[list[MeshInfo], wp.array, wp.array]:
    """Warp meshes of `specs` [(vertices, faces, restitution, friction, kinematic)] -> (MeshInfo list,
    kinematic vertices, their velocities). Every kinematic mesh's vertices and velocities are views into
    one array each, so a substep moves all of them (every world's fingers) in one launch."""
    kin_verts = [m[0] for m in specs if m[4]]
    kin_count = sum(v.shape[0] for v in kin_verts)
    kin_points = wp.array(np.concatenate(kin_verts) if kin_verts else np.zeros((0, 3), np.float32),
                          dtype=wp.vec3, device=device)
    kin_velocities = wp.zeros(kin_count, dtype=wp.vec3, device=device)
    meshes: list[MeshInfo] = []
    face_offset = kin_offset = 0
    for verts, faces, e, mu, kin in specs:
        nv = verts.shape[0]
        if kin:
            points = kin_points[kin_offset: kin_offset + nv]
            velocities = kin_velocities[kin_offset: kin_offset + nv]
        else:
            points = wp.array(verts, dtype=wp.vec3, device=device)
            velocities = wp.zeros(nv, dtype=wp.vec3, device=device)
        mesh = wp.Mesh(points=points, indices=wp.array(faces.reshape(-1), dtype=wp.int32, device=device),
                       velocities=velocities)
        meshes.append(MeshInfo(mesh, faces, verts, e, mu, kin, face_offset, kin_offset if kin else -1))
        face_offset += faces.shape[0]
        kin_offset += nv if kin else 0
    return meshes, kin_points, kin_velocities


class ModelBuilder:
    """Collects bodies, control points and meshes, then :meth:`finalize` makes a model."""

    def __init__(self, params: SimParams | None = None):
        self.params = params if params is not None else SimParams()
        self._x: list[np.ndarray] = []
        self._v: list[np.ndarray] = []
        self._mass: list[np.ndarray] = []
        self._body: list[np.ndarray] = []
        self._springs: list[np.ndarray] = []
        self._rest: list[np.ndarray] = []
        self._logy: list[np.ndarray] = []
        self._ctrl: list[np.ndarray] = []
        self._ctrl_springs: list[np.ndarray] = []  # (c_global, particle)
        self._ctrl_rest: list[np.ndarray] = []
        self._ctrl_logy: list[np.ndarray] = []
        self._meshes: list[tuple[np.ndarray, np.ndarray, float, float, bool]] = []
        self._n = 0
        self._nc = 0

    @property
    def num_particles(self) -> int:
        return self._n

    def _log_y(self, spring_Y, m: int) -> np.ndarray:
        y = _per_item("spring_Y", spring_Y, m, positive=True)
        return np.log(y).astype(np.float32)

    def add_body(self, points, *, radius: float = 0.02, max_neighbors: int = 30, spring_Y=3e4,
                 mass=1.0, springs=None, rest_lengths=None, velocities=None) -> int:
        """Add a body; springs by the radius rule unless ``springs`` (M, 2 local indices) is given.

        ``spring_Y`` is a scalar or one value per spring; ``mass`` a scalar or one value per particle.
        Rest lengths come from ``points`` unless ``rest_lengths`` is given. Returns the body id.
        """
        pts = _points("points", points)
        n = pts.shape[0]
        radius = _positive("radius", radius)
        max_neighbors = _count("max_neighbors", max_neighbors)
        masses = _per_item("mass", mass, n, positive=True)
        vel = np.zeros((n, 3)) if velocities is None else _points("velocities", velocities)
        if vel.shape != pts.shape:
            raise ValueError(f"velocities must have shape {pts.shape} like points, got {vel.shape}")
        if springs is None:
            pairs = radius_springs(pts, radius, max_neighbors)
        else:
            pairs = np.asarray(springs)
            bad_dtype = pairs.size and not np.issubdtype(pairs.dtype, np.integer)
            if pairs.ndim != 2 or pairs.shape[1] != 2 or bad_dtype:
                raise ValueError(f"springs must be an (M, 2) integer array, got shape {pairs.shape}")
            if pairs.size and (pairs.min() < 0 or pairs.max() >= n):
                raise ValueError(f"springs index particles outside [0, {n}) of this body")
            pairs = pairs.astype(np.int32).reshape(-1, 2)
        m = pairs.shape[0]
        if rest_lengths is None:
            rest = _rest_lengths(pts[pairs[:, 0]], pts[pairs[:, 1]])
        else:
            rest = _per_item("rest_lengths", rest_lengths, m, positive=True).astype(np.float32)
        if m and np.any(rest <= 0):
            raise ValueError("rest_lengths must be > 0 (coincident particles make a 0/0 strain)")
        body = len(self._x)
        self._springs.append(pairs + self._n)
        self._rest.append(rest)
        self._logy.append(self._log_y(spring_Y, m))
        self._x.append(pts.astype(np.float32))
        self._v.append(vel.astype(np.float32))
        self._mass.append(masses.astype(np.float32))
        self._body.append(np.full(n, body, dtype=np.int32))
        self._n += n
        return body

    def add_control_points(self, points, *, radius: float = 0.04, max_neighbors: int = 50, spring_Y=3e4,
                           springs=None, rest_lengths=None) -> slice:
        """Add kinematic control points, each tied by springs to the object particles within ``radius``
        (nearest first, at most ``max_neighbors``; no de-duplication or rest filter, as PhysTwin).
        ``springs`` may give (M, 2) pairs (local control index, global particle index) instead.
        Returns the slice of the new points in the control arrays."""
        pts = _points("points", points)
        if self._n == 0:
            raise ValueError("add bodies before control points (control springs attach to particles)")
        radius = _positive("radius", radius)
        max_neighbors = _count("max_neighbors", max_neighbors)
        k = pts.shape[0]
        allx = np.concatenate(self._x)
        if springs is None:
            allx64 = allx.astype(np.float64)
            rows = []
            nbr_lists = _sorted_neighbours(cKDTree(allx64), allx64, pts, radius, max_neighbors,
                                           exclude_self=False)
            for c, nbrs in enumerate(nbr_lists):
                rows += [(c, j) for j in nbrs.tolist()]
            pairs = np.asarray(rows, dtype=np.int32).reshape(-1, 2)
        else:
            pairs = np.asarray(springs)
            if pairs.ndim != 2 or pairs.shape[1] != 2:
                raise ValueError(f"springs must be an (M, 2) integer array, got shape {pairs.shape}")
            if pairs.size and (pairs[:, 0].min() < 0 or pairs[:, 0].max() >= k
                               or pairs[:, 1].min() < 0 or pairs[:, 1].max() >= self._n):
                raise ValueError("springs must hold (control index < K, particle index < num_particles)")
            pairs = pairs.astype(np.int32).reshape(-1, 2)
        m = pairs.shape[0]
        if rest_lengths is None:
            rest = _rest_lengths(pts[pairs[:, 0]], allx[pairs[:, 1]])
        else:
            rest = _per_item("rest_lengths", rest_lengths, m, positive=True).astype(np.float32)
        if m and np.any(rest <= 0):
            raise ValueError("a control point coincides with a particle (rest length 0): offset it")
        self._ctrl.append(pts.astype(np.float32))
        self._ctrl_springs.append(pairs + np.array([self._nc, 0], dtype=np.int32))
        self._ctrl_rest.append(rest)
        self._ctrl_logy.append(self._log_y(spring_Y, m))
        out = slice(self._nc, self._nc + k)
        self._nc += k
        return out

    def _add_mesh(self, vertices, faces, restitution, friction, kinematic) -> int:
        verts = _points("vertices", vertices)
        f = np.asarray(faces)
        if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0 or not np.issubdtype(f.dtype, np.integer):
            raise ValueError(f"faces must be a non-empty (F, 3) integer array, got shape {f.shape}")
        if f.min() < 0 or f.max() >= verts.shape[0]:
            raise ValueError(f"faces index vertices outside [0, {verts.shape[0]})")
        e, mu = _restitution_friction(restitution, friction)
        self._meshes.append((verts.astype(np.float32), f.astype(np.int32), e, mu, kinematic))
        return len(self._meshes) - 1

    def add_static_mesh(self, vertices, faces, *, restitution: float = 0.0, friction: float = 0.5) -> int:
        """Add a fixed, closed triangle mesh collider (box, clip, table edge). Returns its mesh id."""
        return self._add_mesh(vertices, faces, restitution, friction, kinematic=False)

    def add_kinematic_mesh(self, vertices, faces, *, restitution: float = 0.0, friction: float = 0.5) -> int:
        """Add a closed triangle mesh whose vertices are driven per frame through
        :meth:`Control.set_kinematic_mesh` (gripper finger, pusher). Returns its mesh id."""
        return self._add_mesh(vertices, faces, restitution, friction, kinematic=True)

    def finalize(self, device: str = "cpu", *, requires_grad: bool = False,
                 num_worlds: int = 1) -> SpringMassModel:
        """Build the model's device arrays.

        ``num_worlds`` > 1 replicates everything added (particles, springs, control points, meshes) into
        independent worlds laid out world-major: world ``w`` owns particles ``[w*n, (w+1)*n)``, its own
        control points and meshes, and never touches another world (springs, contacts and collision
        candidates stay inside it). Within a world the order of particles, springs and meshes is the
        single-world order, so each world computes bit-identically to a model built with one world.
        """
        if self._n == 0:
            raise ValueError("the builder has no particles: call add_body first")
        check_device(device)
        worlds = _count("num_worlds", num_worlds)
        nw, cw = self._n, self._nc
        n = nw * worlds
        obj_w = np.concatenate(self._springs).astype(np.int64)
        ctrl_w = np.concatenate(self._ctrl_springs or [np.zeros((0, 2))]).astype(np.int64)
        obj_springs = np.concatenate([obj_w + w * nw for w in range(worlds)]).astype(np.int32).reshape(-1, 2)
        # control point c of world w is index n + w * cw + c; its particle is shifted into world w
        ctrl_enc = np.concatenate(
            [ctrl_w + np.array([n + w * cw, w * nw]) for w in range(worlds)]
        ).astype(np.int32).reshape(-1, 2)
        springs = np.concatenate([obj_springs, ctrl_enc]).astype(np.int32)
        rest = np.concatenate(self._rest * worlds + self._ctrl_rest * worlds).astype(np.float32)
        logy = np.concatenate(self._logy * worlds + self._ctrl_logy * worlds).astype(np.float32)
        masses = np.tile(np.concatenate(self._mass), worlds)
        body = np.tile(np.concatenate(self._body), worlds)
        masks = np.arange(n, dtype=np.int32) if self.params.self_collision else body
        ctrl_x0 = np.tile(np.concatenate(self._ctrl or [np.zeros((0, 3), np.float32)]), (worlds, 1))

        # incident springs per particle in spring order: +(s+1) first end, -(s+1) second end
        s_idx = np.arange(springs.shape[0], dtype=np.int64)
        ends = np.concatenate([springs[:, 0], springs[:, 1]]).astype(np.int64)
        signed = np.concatenate([s_idx + 1, -(s_idx + 1)])
        sid = np.concatenate([s_idx, s_idx])
        keep = ends < n
        ends, signed, sid = ends[keep], signed[keep], sid[keep]
        order = np.lexsort((sid, ends))
        inc = signed[order].astype(np.int32)
        inc_off = np.zeros(n + 1, dtype=np.int32)
        np.cumsum(np.bincount(ends, minlength=n), out=inc_off[1:])

        # spring neighbours per particle (sorted), excluded from particle-particle contact, unless
        # collision_exclusion is "none" (PhysTwin's rule: no pair is excluded)
        excl = obj_springs if self.params.collision_exclusion == "springs" else obj_springs[:0]
        a, b = excl[:, 0].astype(np.int64), excl[:, 1].astype(np.int64)
        pa = np.concatenate([a, b])
        pb = np.concatenate([b, a])
        key = np.unique(pa * n + pb)
        nbr = (key % n).astype(np.int32)
        nbr_off = np.zeros(n + 1, dtype=np.int32)
        np.cumsum(np.bincount(key // n, minlength=n), out=nbr_off[1:])

        dev = device
        meshes, kin_points, kin_velocities = device_meshes(self._meshes * worlds, dev)
        nm = len(self._meshes)
        nm = len(self._meshes)

        def arr(a, dtype, grad=False):
            return wp.array(a, dtype=dtype, device=dev, requires_grad=grad)

        return SpringMassModel(
            params=self.params,
            device=str(dev),
            num_particles=n,
            num_control_points=cw * worlds,
            num_object_springs=int(obj_springs.shape[0]),
            springs_np=springs,
            rest_lengths_np=rest,
            log_y_np=logy,
            masses_np=masses,
            body_id_np=body,
            x0_np=np.tile(np.concatenate(self._x), (worlds, 1)),
            v0_np=np.tile(np.concatenate(self._v), (worlds, 1)),
            control_x0_np=ctrl_x0.astype(np.float32),
            springs=arr(springs, wp.vec2i),
            rest_lengths=arr(rest, float),
            log_y=arr(logy, float, requires_grad),
            masses=arr(masses, float),
            masks=arr(masks, int),
            inc_offsets=arr(inc_off, int),
            inc_springs=arr(inc, int),
            nbr_offsets=arr(nbr_off, int),
            nbr=arr(nbr, int),
            meshes=meshes,
            requires_grad=requires_grad,
            num_worlds=worlds,
            kin_points=kin_points,
            kin_velocities=kin_velocities,
            particle_world=arr(np.repeat(np.arange(worlds, dtype=np.int32), nw), int),
            contact_coeffs=arr(np.array([self.params.ground_restitution, self.params.ground_friction,
                                         self.params.object_restitution, self.params.object_friction],
                                        np.float32), float, requires_grad),
            world_mesh_start=arr(np.arange(worlds + 1, dtype=np.int32) * nm, int),
        )
