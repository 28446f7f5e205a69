"""RobotModel: a URDF's kinematic tree, limits, mimic joints and link meshes; vectorised forward kinematics.

The model is a data object (built once by `load_robot`); poses are float64 4x4 matrices in the world
frame (= the URDF root frame). The configuration vector `q` holds the actuated joints (revolute,
continuous, prismatic; mimic joints excluded) in URDF tree order; `model.joint_names` names them.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from xml.etree import ElementTree

import numpy as np
import trimesh

from twinbench.errors import InputError

_MOVING = ("revolute", "continuous", "prismatic")


class URDFError(InputError):
    """A URDF that cannot be turned into a RobotModel (message names the file and the fix)."""


CONVEX_CONTACT_FACES = 1000  # faces of a simplified convex contact mesh (`convex_contact_mesh`)
HEAVY_CONTACT_FACES = 5000  # a contact mesh above this makes physics steps slow: warned at build
_FK_MEMO = 256  # configurations RobotModel.fk remembers (a step of 64 worlds asks for a few per world)


@dataclass(frozen=True)
class JointSpec:
    """One URDF joint. `q_index` is its slot in q (None for fixed and mimic joints)."""

    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray  # (4, 4) parent link -> joint frame at zero
    axis: np.ndarray  # (3,) unit axis in the joint frame
    lower: float
    upper: float
    q_index: int | None
    mimic: tuple[str, float, float] | None = None  # (source joint, multiplier, offset)


@dataclass
class RobotModel:
    """Kinematic tree + geometry of a robot. Build with `load_robot` (or `load_builtin_arm`)."""

    name: str
    urdf_path: Path
    link_names: list[str]  # root first, parents before children
    joints: list[JointSpec]  # tree order; joints[i] moves link_names[i + 1]
    joint_names: list[str]  # actuated joints, in q order
    lower: np.ndarray  # (n_q,)
    upper: np.ndarray  # (n_q,)
    ee_link: str
    ee_offset: np.ndarray  # (4, 4) fixed offset from ee_link to the end-effector frame
    visual_meshes: dict[str, trimesh.Trimesh] = field(default_factory=dict)  # link frame
    collision_meshes: dict[str, trimesh.Trimesh] = field(default_factory=dict)  # link frame
    link_colors: dict[str, np.ndarray] = field(default_factory=dict)  # rgb in [0, 1] from URDF materials
    gripper_joint: str | None = None  # actuated joint driving the fingers (mimics follow it)
    gripper_open: float = 0.0  # gripper joint value when fully open (command 0)
    gripper_closed: float = 0.0  # gripper joint value when fully closed (command 1)
    contact_links: tuple[str, ...] = ()  # links whose collision meshes touch objects (fingers, pusher)
    home_q: np.ndarray | None = None  # (n_q,) default configuration
    # contact links whose meshes are convex hulls (`with_convex_contacts`): how far (m) each moved at most
    convex_contact_moved: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.ee_offset = np.asarray(self.ee_offset, dtype=np.float64).reshape(4, 4)
        self._link_index = {name: i for i, name in enumerate(self.link_names)}
        if self.ee_link not in self._link_index:
            raise URDFError(
                f"{self.urdf_path}: ee_link {self.ee_link!r} is not a link; links: {self.link_names}"
            )
        for link in self.contact_links:
            if link not in self._link_index:
                raise URDFError(
                    f"{self.urdf_path}: contact link {link!r} is not a link; links: {self.link_names}"
                )
        qi = {name: i for i, name in enumerate(self.joint_names)}
        if self.gripper_joint is not None and self.gripper_joint not in qi:
            raise URDFError(
                f"{self.urdf_path}: gripper_joint {self.gripper_joint!r} is not an actuated joint; "
                f"actuated joints: {self.joint_names}"
            )
        if self.home_q is None:
            self.home_q = np.clip(np.zeros(self.n_q), self.lower, self.upper)
        self.home_q = self.check_q(self.home_q, "home_q")
        # Precomputed per-joint arrays for FK.
        self._parent = np.array([self._link_index[j.parent] for j in self.joints], dtype=np.int64)
        self._child = np.array([self._link_index[j.child] for j in self.joints], dtype=np.int64)
        self._skew = []
        for j in self.joints:
            x, y, z = j.axis
            k1 = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
            self._skew.append((k1, k1 @ k1))
        self._source = []  # (q index, multiplier, offset) or None for fixed joints
        for j in self.joints:
            if j.type == "fixed":
                self._source.append(None)
            elif j.mimic is not None:
                src, mult, off = j.mimic
                self._source.append((qi[src], mult, off))
            else:
                self._source.append((j.q_index, 1.0, 0.0))
        # Arm joints: actuated joints on the path root -> ee_link, in order (used by IK).
        chain = []
        link = self.ee_link
        by_child = {j.child: j for j in self.joints}
        while link in by_child:
            j = by_child[link]
            if j.q_index is not None:
                chain.append(j)
            link = j.parent
        chain.reverse()
        self.arm_joints = [j.name for j in chain]
        self.arm_q_indices = np.array([j.q_index for j in chain], dtype=np.int64)
        self._arm_joint_rows = np.array([self.joints.index(j) for j in chain], dtype=np.int64)
        self._arm_prismatic = np.array([j.type == "prismatic" for j in chain])
        self._arm_axes = np.array([j.axis for j in chain], dtype=np.float64).reshape(-1, 3)  # joint frames
        self._fk_memo: dict[bytes, np.ndarray] = {}  # fk's link poses of recent configurations

    # ----------------------------------------------------------------- basic facts
    @property
    def n_q(self) -> int:
        return len(self.joint_names)

    @property
    def n_links(self) -> int:
        return len(self.link_names)

    @property
    def fixed_links(self) -> np.ndarray:
        """(n_links,) bool: the links whose world pose does not depend on q (the root and the links fixed
        to it by fixed joints only)."""
        fixed = np.zeros(self.n_links, dtype=bool)
        fixed[0] = True
        for k in range(len(self.joints)):  # tree order: a parent is decided before its children
            fixed[self._child[k]] = self._source[k] is None and fixed[self._parent[k]]
        return fixed

    def link_index(self, link: str) -> int:
        if link not in self._link_index:
            raise KeyError(f"unknown link {link!r}; links: {self.link_names}")
        return self._link_index[link]

    def joint(self, name: str) -> JointSpec:
        for j in self.joints:
            if j.name == name:
                return j
        raise KeyError(f"unknown joint {name!r}; joints: {[j.name for j in self.joints]}")

    def check_q(self, q: np.ndarray, name: str = "q") -> np.ndarray:
        """Validate a (n_q,) or (B, n_q) configuration: shape and finiteness (raises ValueError)."""
        q = np.asarray(q, dtype=np.float64)
        if q.ndim not in (1, 2) or q.shape[-1] != self.n_q:
            raise ValueError(f"{name}: expected shape ({self.n_q},) or (B, {self.n_q}), got {q.shape}")
        if not np.all(np.isfinite(q)):
            raise ValueError(f"{name}: contains NaN or inf")
        return q

    def clip_q(self, q: np.ndarray) -> np.ndarray:
        return np.clip(q, self.lower, self.upper)

    # ----------------------------------------------------------------- gripper
    def set_gripper(self, q: np.ndarray, closedness: float | np.ndarray) -> np.ndarray:
        """Copy of q with the gripper joint set from a command in [0, 1] (1 = closed); no-op without one."""
        q = np.array(q, dtype=np.float64)
        if self.gripper_joint is None:
            return q
        c = np.clip(closedness, 0.0, 1.0)
        q[..., self.joint_names.index(self.gripper_joint)] = self.gripper_open + c * (
            self.gripper_closed - self.gripper_open
        )
        return q

    def gripper_closedness(self, q: np.ndarray) -> np.ndarray | float:
        """Gripper command in [0, 1] (1 = closed) encoded by q's gripper joint (0.0 without a gripper)."""
        if self.gripper_joint is None or self.gripper_closed == self.gripper_open:
            return 0.0
        v = np.asarray(q)[..., self.joint_names.index(self.gripper_joint)]
        return (v - self.gripper_open) / (self.gripper_closed - self.gripper_open)

    def gripper_opening(self, q: np.ndarray) -> np.ndarray | float:
        """Distance between two symmetric prismatic fingers, 2 |q_g - closed| (0 without a gripper)."""
        if self.gripper_joint is None:
            return 0.0
        v = np.asarray(q)[..., self.joint_names.index(self.gripper_joint)]
        return 2.0 * np.abs(v - self.gripper_closed)

    # ----------------------------------------------------------------- kinematics
    def _fk(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(B, n_q) -> link poses (B, n_links, 4, 4) and joint frames (B, n_joints, 4, 4)."""
        b = q.shape[0]
        links = np.empty((b, self.n_links, 4, 4))
        links[:, 0] = np.eye(4)
        frames = np.empty((b, len(self.joints), 4, 4))
        for k, j in enumerate(self.joints):
            jf = links[:, self._parent[k]] @ j.origin
            frames[:, k] = jf
            src = self._source[k]
            if src is None:
                links[:, self._child[k]] = jf
                continue
            value = q[:, src[0]] * src[1] + src[2]
            child = jf.copy()
            if j.type == "prismatic":
                child[:, :3, 3] += (jf[:, :3, :3] @ j.axis) * value[:, None]
            else:  # Rodrigues with the joint's precomputed skew matrix K: R = I + sin K + (1 - cos) K^2
                k1, k2 = self._skew[k]
                s, c = np.sin(value)[:, None, None], (1.0 - np.cos(value))[:, None, None]
                rot = np.eye(3) + s * k1 + c * k2
                child[:, :3, :3] = jf[:, :3, :3] @ rot
            links[:, self._child[k]] = child
        return links, frames

    def fk(self, q: np.ndarray) -> np.ndarray:
        """World poses of every link: q (n_q,) -> (n_links, 4, 4); q (B, n_q) -> (B, n_links, 4, 4).

        The poses of the last few hundred configurations are remembered (an env step asks for the same q
        for posing the Gaussians, the wrist camera and the observation); callers get their own copy."""
        q = self.check_q(q)
        rows = np.atleast_2d(q)
        keys = [r.tobytes() for r in rows]
        memo = self._fk_memo
        known = [memo.get(k) for k in keys]
        if all(t is not None for t in known):
            links = np.stack(known)
        else:
            links, _ = self._fk(rows)
            if len(memo) + len(keys) > _FK_MEMO:
                memo.clear()
            memo.update(zip(keys, links.copy(), strict=True))
        return links[0] if q.ndim == 1 else links

    def link_pose(self, q: np.ndarray, link: str) -> np.ndarray:
        """World pose(s) of one link."""
        return self.fk(q)[..., self.link_index(link), :, :]

    def ee_pose(self, q: np.ndarray) -> np.ndarray:
        """World pose(s) of the end-effector frame (ee_link @ ee_offset)."""
        return self.link_pose(q, self.ee_link) @ self.ee_offset

    def ee_pose_and_jacobian(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(B, n_q) -> EE poses (B, 4, 4) and geometric Jacobians (B, 6, n_arm) over `arm_joints`.

        Rows 0-2: linear velocity of the EE origin (world); rows 3-5: angular velocity (world).
        """
        q = self.check_q(q)
        links, frames = self._fk(np.atleast_2d(q))
        ee = links[:, self._link_index[self.ee_link]] @ self.ee_offset
        jf = frames[:, self._arm_joint_rows]  # (B, n_arm, 4, 4)
        axes = np.einsum("bkij,kj->bki", jf[:, :, :3, :3], self._arm_axes)
        lever = ee[:, None, :3, 3] - jf[:, :, :3, 3]
        jv = np.where(self._arm_prismatic[None, :, None], axes, np.cross(axes, lever))
        jw = np.where(self._arm_prismatic[None, :, None], 0.0, axes)
        jac = np.concatenate([jv, jw], axis=2).transpose(0, 2, 1)
        return ee, jac

    # ----------------------------------------------------------------- geometry
    def contact_faces(self, link: str) -> np.ndarray:
        """(F, 3) int32 faces of a contact link's collision mesh (fixed over time)."""
        return np.asarray(self._contact_mesh(link).faces, dtype=np.int32)

    def _contact_mesh(self, link: str) -> trimesh.Trimesh:
        if link not in self.collision_meshes:
            raise KeyError(
                f"link {link!r} has no collision mesh; links with one: {list(self.collision_meshes)}"
            )
        return self.collision_meshes[link]

    def _posed_contact_vertices(self, t: np.ndarray, link: str) -> np.ndarray:
        """A link's collision-mesh vertices moved by its pose(s) t (..., 4, 4) -> (..., V, 3)."""
        v = np.asarray(self._contact_mesh(link).vertices, dtype=np.float64)
        return np.einsum("...ij,vj->...vi", t[..., :3, :3], v) + t[..., None, :3, 3]

    def contact_vertices(self, q: np.ndarray, link: str) -> np.ndarray:
        """World-frame vertices (V, 3) (or (B, V, 3) for batched q) of a link's collision mesh at q."""
        return self._posed_contact_vertices(self.link_pose(q, link), link)

    def contact_mesh_frames(
        self, q_from: np.ndarray, q_to: np.ndarray
    ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Frame-start and frame-end world vertices of every contact link: {link: (verts_from, verts_to)}.

        This is what a physics engine that interpolates kinematic mesh vertices linearly across substeps
        needs (faces: `contact_faces(link)`). Both ends come from one batched FK.
        """
        q = np.stack([self.check_q(q_from, "q_from"), self.check_q(q_to, "q_to")])
        t = self.fk(q)
        out = {}
        for link in self.contact_links:
            w = self._posed_contact_vertices(t[:, self.link_index(link)], link)
            out[link] = (w[0], w[1])
        return out

    def interpolate(self, q_from: np.ndarray, q_to: np.ndarray, alpha: float | np.ndarray) -> np.ndarray:
        """Joint-space linear interpolation (1 - alpha) q_from + alpha q_to (alpha scalar or (B,))."""
        q_from = self.check_q(q_from, "q_from")
        q_to = self.check_q(q_to, "q_to")
        a = np.asarray(alpha, dtype=np.float64)
        if a.ndim == 1:
            a = a[:, None]
        return (1.0 - a) * q_from + a * q_to

    def with_convex_contacts(self, max_faces: int = CONVEX_CONTACT_FACES) -> RobotModel:
        """A copy whose contact links collide through their collision meshes' convex hulls (MuJoCo's rule
        for every mesh), each of at most `max_faces` faces (`convex_contact_mesh`; how far each moved is
        in `convex_contact_moved`). A hull fills a link's concavities: a jaw whose grasping side is
        hollow needs a collision mesh of its own."""
        import dataclasses

        meshes, moved = dict(self.collision_meshes), {}
        for link in self.contact_links:
            try:
                meshes[link], moved[link] = convex_contact_mesh(self._contact_mesh(link), max_faces)
            except ValueError as e:
                raise URDFError(f"{self.urdf_path}: contact link {link!r}: {e}") from None
        return dataclasses.replace(self, collision_meshes=meshes, convex_contact_moved=moved)

    def contact_vertices_interpolated(
        self, q_from: np.ndarray, q_to: np.ndarray, alpha, link: str
    ) -> np.ndarray:
        """World vertices of a contact link at the joint-space interpolation of q_from and q_to."""
        return self.contact_vertices(self.interpolate(q_from, q_to, alpha), link)


def convex_contact_mesh(
    mesh: trimesh.Trimesh, max_faces: int = CONVEX_CONTACT_FACES
) -> tuple[trimesh.Trimesh, float]:
    """The convex hull of `mesh` with at most `max_faces` faces, and how far (m) its surface lies inside
    the exact hull at most (0 when the exact hull is small enough).

    A curved CAD part's hull keeps thousands of faces; then the hull's vertices are binned in cubic cells,
    one kept per cell (the farthest from the centre, so the extremes stay), the cell growing until the
    hull of the kept ones is small enough. It lies inside the exact hull, and the distance returned is
    the exact Hausdorff distance between the two (attained at an exact hull vertex)."""
    if max_faces < 4:
        raise ValueError(f"max_faces must be at least 4 (a tetrahedron), got {max_faces}")
    v = np.asarray(mesh.vertices, dtype=np.float64)
    if len(v) < 4 or np.linalg.matrix_rank(v - v.mean(axis=0), tol=1e-9) < 3:
        raise ValueError("its collision mesh is flat or has under 4 vertices: it has no convex hull with "
                         "volume")
    hull = trimesh.convex.convex_hull(v)
    if len(hull.faces) <= max_faces:
        return hull, 0.0
    pts = np.asarray(hull.vertices)
    far = np.linalg.norm(pts - pts.mean(axis=0), axis=1)
    cell = float(np.max(hull.extents)) / 128.0
    while True:
        keys = np.floor(pts / cell).astype(np.int64)
        order = np.lexsort((-far, keys[:, 2], keys[:, 1], keys[:, 0]))  # per cell, the farthest first
        k = keys[order]
        first = np.ones(len(k), dtype=bool)
        first[1:] = np.any(k[1:] != k[:-1], axis=1)
        kept = pts[order[first]]
        if len(kept) >= 4 and np.linalg.matrix_rank(kept - kept.mean(axis=0), tol=1e-9) == 3:
            small = trimesh.convex.convex_hull(kept)
            if len(small.faces) <= max_faces:
                _, dist, _ = trimesh.proximity.closest_point(small, pts)
                return small, float(np.max(dist))
        cell *= 1.2


# ===================================================================== loading
def _check_finite(urdf_path: Path, what: str, values) -> None:
    """URDFError naming the element when any value is NaN or infinite."""
    if not np.all(np.isfinite(np.asarray(values, dtype=np.float64))):
        raise URDFError(f"{urdf_path}: {what} holds NaN or inf; give finite numbers")


def _tree_order(urdf_path: Path, links: list[str], joints) -> tuple[list[str], list, dict[str, int]]:
    """Links root first (breadth-first), the joints in that order and each link's depth.

    Refuses, before any traversal, every joint graph that is not a tree: duplicate names, unknown links,
    a link with two parent joints, a joint from a link to itself, no single root, a cycle, a link not
    connected to the root."""
    dupes = sorted({n for n in links if links.count(n) > 1}) if len(set(links)) != len(links) else []
    if dupes:
        raise URDFError(f"{urdf_path}: link name(s) {dupes} defined more than once; rename them")
    if not links:
        raise URDFError(f"{urdf_path}: no <link> elements; a robot needs at least one link")
    known = set(links)
    parent_of: dict[str, str] = {}
    for j in joints:
        for end in (j.parent, j.child):
            if end not in known:
                raise URDFError(f"{urdf_path}: joint {j.name!r} refers to unknown link {end!r}")
        if j.parent == j.child:
            raise URDFError(f"{urdf_path}: joint {j.name!r} connects link {j.child!r} to itself")
        if j.child in parent_of:
            raise URDFError(
                f"{urdf_path}: link {j.child!r} is the child of two joints (from {parent_of[j.child]!r} and "
                f"{j.parent!r}); a URDF's joints must form a tree (no loops)"
            )
        parent_of[j.child] = j.parent
    roots = [name for name in links if name not in parent_of]
    if len(roots) != 1:
        what = "a cycle (every link has a parent)" if not roots else f"several: {roots}"
        raise URDFError(f"{urdf_path}: expected exactly one root link, found {what}; the joints must "
                        "form a tree")
    by_parent: dict[str, list] = {}
    for j in joints:
        by_parent.setdefault(j.parent, []).append(j)
    order, joints_sorted, queue, depth = [roots[0]], [], [roots[0]], {roots[0]: 0}
    while queue:  # each link has at most one parent, so each is queued at most once
        parent = queue.pop(0)
        for j in by_parent.get(parent, []):
            if j.child in depth:  # unreachable with one parent per link; kept as a hard stop
                raise URDFError(f"{urdf_path}: joint {j.name!r} closes a loop at link {j.child!r}")
            joints_sorted.append(j)
            order.append(j.child)
            depth[j.child] = depth[parent] + 1
            queue.append(j.child)
    if len(order) != len(links):
        raise URDFError(
            f"{urdf_path}: links not connected to the root {roots[0]!r} (a loop among them?): "
            f"{sorted(set(links) - set(order))}; the joints must form a tree"
        )
    return order, joints_sorted, depth


def _inside(path: Path, root: Path) -> bool:
    """Whether `path` (symlinks resolved) lies in the directory tree of `root`."""
    try:
        return path.resolve().is_relative_to(root.resolve())
    except (OSError, RuntimeError, ValueError):  # symlink loop, bad name
        return False


def _resolve_filename(
    filename: str, urdf_dir: Path, package_dirs: Sequence[Path]
) -> tuple[Path | None, list[Path]]:
    """Resolve a mesh filename (package://, file://, relative, absolute) -> (path or None, tried).

    A path is only ever looked at (is_file) once it is known to lie inside its allowed tree: a
    package:// path inside its package folder, any other path inside the URDF's folder or one of
    `package_dirs`. Anything else raises URDFError without touching the file."""
    tried: list[Path] = []
    if not filename:
        raise URDFError("<mesh> has no filename attribute")
    if "\x00" in filename:
        raise URDFError(f"mesh filename {filename!r} holds a NUL character")
    if filename.startswith("package://"):
        rest = filename[len("package://") :]
        pkg, _, rel = rest.partition("/")
        if not pkg or pkg in (".", "..") or ".." in Path(rel).parts or Path(rel).is_absolute():
            raise URDFError(
                f"mesh {filename!r} leaves its package folder ('..' or an absolute path); "
                "give a path inside the package"
            )
        roots = list(package_dirs)
        roots += [Path(p) for p in os.environ.get("ROS_PACKAGE_PATH", "").split(os.pathsep) if p]
        roots += [urdf_dir, *urdf_dir.parents]
        for root in roots:
            cands = [(root / pkg, root / pkg / rel)] + ([(root, root / rel)] if root.name == pkg else [])
            for pkg_dir, c in cands:
                if not _inside(c, pkg_dir):  # e.g. a symlink in the package pointing elsewhere
                    continue
                tried.append(c)
                if c.is_file():
                    return c, tried
        # A description copied out of its package (example-robot-data's so_arm_description, say, whose
        # meshes are `package://example-robot-data/robots/so_arm_description/meshes/...`): the path's
        # tails of at least a folder and a file, longest first, under the URDF's folder and its parents.
        parts = Path(rel).parts
        for k in range(1, len(parts) - 1):
            tail = Path(*parts[k:])
            for root in [*package_dirs, urdf_dir, *urdf_dir.parents]:
                c = root / tail
                if _inside(c, root) and c.is_file():
                    tried.append(c)
                    return c, tried
        return None, tried
    if filename.startswith("file://"):
        filename = filename[len("file://") :]
    p = Path(filename)
    p = p if p.is_absolute() else urdf_dir / p
    allowed = [urdf_dir, *package_dirs]
    if not any(_inside(p, root) for root in allowed):
        raise URDFError(
            f"mesh {filename!r} lies outside the URDF's folder {urdf_dir}; refusing to read it. Move the "
            "mesh into that folder (or pass its folder in package_dirs)"
        )
    tried.append(p)
    return (p if p.is_file() else None), tried


def urdf_mesh_files(urdf_path: str | Path) -> list[tuple[str, Path]]:
    """(filename as written, resolved file) of every <mesh> a URDF references (visual and collision;
    resolved as `load_robot` does, with no package_dirs); a mesh not found is left out."""
    urdf_path = Path(urdf_path).resolve()
    try:
        root = ElementTree.fromstring(urdf_path.read_bytes())
    except ElementTree.ParseError as exc:
        raise URDFError(f"{urdf_path}: malformed XML ({exc}); fix the file") from exc
    out = {}
    for mesh in root.iter("mesh"):
        name = mesh.get("filename", "")
        try:
            path, _ = _resolve_filename(name, urdf_path.parent, ())
        except URDFError as exc:
            raise URDFError(f"{urdf_path}: {exc}") from None
        if path is not None:
            out[name] = path
    return list(out.items())


def _check_size(urdf_path: Path, link: str, what: str, values, n: int) -> np.ndarray:
    try:
        arr = np.asarray(values, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        arr = np.array([])
    if arr.size != n or not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise URDFError(f"{urdf_path}: link {link!r}: {what} must be {n} finite value(s) > 0, "
                        f"got {arr.tolist()}")
    return arr


def _geometry_mesh(
    geometry, link: str, urdf_path: Path, package_dirs: Sequence[Path]
) -> trimesh.Trimesh | None:
    if geometry is None:
        return None
    if geometry.mesh is not None:
        try:
            path, tried = _resolve_filename(geometry.mesh.filename, urdf_path.parent, package_dirs)
        except URDFError as exc:
            raise URDFError(f"{urdf_path}: link {link!r}: {exc}") from None
        if path is None:
            shown = ", ".join(str(t) for t in tried[:6]) + (" ..." if len(tried) > 6 else "")
            raise FileNotFoundError(
                f"{urdf_path}: link {link!r}: mesh {geometry.mesh.filename!r} not found (tried {shown}); "
                "fix the path, or name the folder holding the package: ROS_PACKAGE_PATH=DIR (any command), "
                "--package-dirs DIR (robot-info) or package_dirs=[DIR] (load_robot)"
            )
        scale = None
        if geometry.mesh.scale is not None:
            scale = np.asarray(geometry.mesh.scale, dtype=np.float64).reshape(-1)
            if scale.size not in (1, 3):
                raise URDFError(f"{urdf_path}: link {link!r}: mesh scale needs 1 or 3 values, got "
                                f"{scale.tolist()}")
            scale = np.broadcast_to(scale, (3,))
            if not np.all(np.isfinite(scale)) or np.any(scale == 0):
                raise URDFError(f"{urdf_path}: link {link!r}: mesh scale {scale.tolist()} must be finite "
                                "and non-zero")
        try:
            mesh = trimesh.load(path, force="mesh", process=False)
            vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)
        except Exception as exc:  # trimesh raises many types for bad files
            raise URDFError(f"{urdf_path}: link {link!r}: cannot read mesh {path}: {exc}") from exc
        if not np.all(np.isfinite(vertices)):
            raise URDFError(f"{urdf_path}: link {link!r}: mesh {path} has NaN or inf vertices; clean it")
        # process=True merges duplicate vertices (STL stores each triangle separately), so closed meshes
        # are watertight: the physics engine's signed-distance queries rely on it.
        mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=True)
        if scale is not None:
            mesh.apply_scale(scale)
        return mesh
    if geometry.box is not None:
        return trimesh.creation.box(extents=_check_size(urdf_path, link, "box size", geometry.box.size, 3))
    if geometry.cylinder is not None:
        r, h = _check_size(urdf_path, link, "cylinder radius and length",
                           [geometry.cylinder.radius, geometry.cylinder.length], 2)
        return trimesh.creation.cylinder(radius=r, height=h, sections=24)
    if geometry.sphere is not None:
        (r,) = _check_size(urdf_path, link, "sphere radius", [geometry.sphere.radius], 1)
        return trimesh.creation.icosphere(subdivisions=2, radius=r)
    return None


def _link_mesh(elements, link: str, urdf_path: Path, package_dirs: Sequence[Path]) -> trimesh.Trimesh | None:
    parts = []
    for el in elements:
        m = _geometry_mesh(el.geometry, link, urdf_path, package_dirs)
        if m is None:
            continue
        if el.origin is not None:
            _check_finite(urdf_path, f"link {link!r} geometry <origin xyz rpy>", el.origin)
            m.apply_transform(np.asarray(el.origin, dtype=np.float64))
        parts.append(m)
    if not parts:
        return None
    return trimesh.util.concatenate(parts) if len(parts) > 1 else parts[0]


def _default_ee_link(order: list[str], depth: dict[str, int], specs: list[JointSpec],
                     gripper_joint: str | None) -> str:
    """The deepest link not carried by a finger joint (ties: the first in tree order). A finger joint moves
    and has no moving joint below it, and is the gripper joint, mimics or is mimicked, or has such a
    sibling (another last moving joint on the same parent link): Franka's Panda, for one, ends in a hand
    with two fingers and a fixed TCP link at one depth, and the TCP, not a finger, is its end effector."""
    moving = [s for s in specs if s.type != "fixed"]
    parent_link = {s.child: s.parent for s in specs}
    has_moving_below = set()
    for s in moving:  # every link above a moving joint has a moving joint below it
        link = s.parent
        while link is not None and link not in has_moving_below:
            has_moving_below.add(link)
            link = parent_link.get(link)
    last = [s for s in moving if s.child not in has_moving_below]
    mimicked = {s.mimic[0] for s in moving if s.mimic is not None}
    fingers = {s.child for s in last if s.name == gripper_joint or s.mimic is not None or s.name in mimicked
               or sum(t.parent == s.parent for t in last) > 1}

    def carried(link: str) -> bool:
        while link is not None:
            if link in fingers:
                return True
            link = parent_link.get(link)
        return False

    candidates = [n for n in order if not carried(n)] or order
    return max(candidates, key=lambda n: (depth[n], -order.index(n)))


def _is_xacro(root: ElementTree.Element) -> bool:
    """Whether a parsed URDF still holds xacro: an element in xacro's namespace or a `${...}` / `$(...)`
    value. A URDF that xacro generated keeps the namespace declaration (and often a comment naming xacro)
    and is a plain URDF."""
    for el in root.iter():
        if el.tag.startswith("{http://www.ros.org/wiki/xacro}"):  # (the parser drops comments)
            return True
        if any("${" in v or "$(" in v for v in el.attrib.values()):
            return True
    return False


def load_robot(
    urdf_path: str | Path,
    *,
    package_dirs: Sequence[str | Path] = (),
    ee_link: str | None = None,
    ee_offset: np.ndarray | None = None,
    gripper_joint: str | None = None,
    gripper_open: float | None = None,
    gripper_closed: float | None = None,
    contact_links: Sequence[str] = (),
    home_q: np.ndarray | None = None,
    load_meshes: bool = True,
) -> RobotModel:
    """Load a URDF (yourdfpy parser) into a RobotModel.

    `package://NAME/rel` paths are searched in `package_dirs`, `ROS_PACKAGE_PATH`, the URDF's folder and
    its parents (both `ROOT/NAME/rel` and, when a folder is itself named NAME, `ROOT/rel`).
    `ee_link` defaults to the deepest link not carried by a gripper's fingers. `gripper_open` /
    `gripper_closed` default to the gripper joint's upper / lower limits.
    """
    import yourdfpy

    urdf_path = Path(urdf_path).expanduser().resolve()
    if not urdf_path.is_file():
        raise FileNotFoundError(f"URDF file not found: {urdf_path}")
    head = urdf_path.read_bytes()
    if b"<!DOCTYPE" in head or b"<!ENTITY" in head:  # entity expansion / external entities: never needed
        raise URDFError(f"{urdf_path}: holds a <!DOCTYPE>/<!ENTITY> declaration, which a URDF never needs "
                        "(entities can expand without bound or read other files); remove it")
    try:  # strict XML check first: yourdfpy silently recovers from malformed XML
        root = ElementTree.fromstring(head)
    except ElementTree.ParseError as exc:
        raise URDFError(f"{urdf_path}: malformed XML ({exc}); fix the file") from exc
    if root.tag != "robot":
        raise URDFError(f"{urdf_path}: root element is <{root.tag}>, expected <robot>")
    if _is_xacro(root):
        raise URDFError(f"{urdf_path}: a xacro file (macros and ${{...}} expressions), not a URDF; expand it "
                        "first: `xacro FILE > robot.urdf` (ROS, or `pip install xacro`)")
    try:
        urdf = yourdfpy.URDF.load(
            str(urdf_path),
            build_scene_graph=False,
            load_meshes=False,
            build_collision_scene_graph=False,
            load_collision_meshes=False,
        )
    except Exception as exc:
        raise URDFError(f"{urdf_path}: not a valid URDF ({type(exc).__name__}: {exc})") from exc
    robot = urdf.robot
    pdirs = [Path(p).expanduser().resolve() for p in package_dirs]

    all_links = [link.name for link in robot.links]
    order, joints_sorted, depth = _tree_order(urdf_path, all_links, robot.joints)

    specs: list[JointSpec] = []
    joint_names: list[str] = []
    lower, upper = [], []
    for j in joints_sorted:
        jtype = j.type
        if jtype not in (*_MOVING, "fixed"):
            raise URDFError(
                f"{urdf_path}: joint {j.name!r}: unsupported type {jtype!r} (use revolute, "
                "continuous, prismatic or fixed)"
            )
        axis = np.array([1.0, 0.0, 0.0]) if j.axis is None else np.asarray(j.axis, dtype=np.float64)
        if axis.shape != (3,):
            raise URDFError(f"{urdf_path}: joint {j.name!r}: <axis xyz> needs 3 values, got {axis.tolist()}")
        _check_finite(urdf_path, f"joint {j.name!r} <axis xyz>", axis)
        if jtype != "fixed":
            n = np.linalg.norm(axis)
            if n < 1e-9:
                raise URDFError(f"{urdf_path}: joint {j.name!r}: zero axis")
            axis = axis / n
        lo, hi = -np.inf, np.inf
        if jtype == "continuous":
            lo, hi = -2 * np.pi, 2 * np.pi  # continuous joints: a bounded range keeps IK well posed
        elif jtype in ("revolute", "prismatic"):
            if j.limit is None or j.limit.lower is None or j.limit.upper is None:
                raise URDFError(f"{urdf_path}: joint {j.name!r} ({jtype}) has no <limit lower upper>")
            lo, hi = float(j.limit.lower), float(j.limit.upper)
            _check_finite(urdf_path, f"joint {j.name!r} <limit lower upper>", np.array([lo, hi]))
            if lo > hi:
                raise URDFError(f"{urdf_path}: joint {j.name!r}: <limit> lower {lo:g} > upper {hi:g}; "
                                "swap them")
        mimic = None
        q_index = None
        if jtype != "fixed" and j.mimic is not None:
            mimic = (
                j.mimic.joint,
                1.0 if j.mimic.multiplier is None else float(j.mimic.multiplier),
                0.0 if j.mimic.offset is None else float(j.mimic.offset),
            )
            _check_finite(urdf_path, f"joint {j.name!r} <mimic multiplier offset>", np.array(mimic[1:]))
        elif jtype != "fixed":
            q_index = len(joint_names)
            joint_names.append(j.name)
            lower.append(lo)
            upper.append(hi)
        origin = np.eye(4) if j.origin is None else np.asarray(j.origin, dtype=np.float64)
        _check_finite(urdf_path, f"joint {j.name!r} <origin xyz rpy>", origin)
        specs.append(JointSpec(j.name, jtype, j.parent, j.child, origin, axis, lo, hi, q_index, mimic))
    for s in specs:
        if s.mimic is not None and s.mimic[0] not in joint_names:
            raise URDFError(
                f"{urdf_path}: mimic joint {s.name!r} follows {s.mimic[0]!r}, which is not an "
                "actuated joint (chained mimics are not supported)"
            )

    visual, collision, colors = {}, {}, {}
    materials = {m.name: m for m in robot.materials if m.name}
    for link in robot.links:
        for vis in link.visuals:
            mat = vis.material
            if mat is not None and mat.color is None and mat.name in materials:
                mat = materials[mat.name]
            if mat is not None and mat.color is not None and mat.color.rgba is not None:
                rgba = np.asarray(mat.color.rgba, dtype=np.float64).reshape(-1)
                if rgba.size != 4 or not np.all(np.isfinite(rgba)):
                    raise URDFError(f"{urdf_path}: link {link.name!r}: material <color rgba> needs 4 finite "
                                    f"values, got {rgba.tolist()}")
                colors[link.name] = np.clip(rgba[:3], 0.0, 1.0)
                break
        if load_meshes:
            v = _link_mesh(link.visuals, link.name, urdf_path, pdirs)
            c = _link_mesh(link.collisions, link.name, urdf_path, pdirs)
            if v is not None:
                visual[link.name] = v
            if c is not None:
                collision[link.name] = c
            elif v is not None:
                collision[link.name] = v

    if ee_link is None:
        ee_link = _default_ee_link(order, depth, specs, gripper_joint)
    g_open = gripper_open
    g_closed = gripper_closed
    if gripper_joint is not None and gripper_joint in joint_names:
        k = joint_names.index(gripper_joint)
        g_open = upper[k] if g_open is None else g_open
        g_closed = lower[k] if g_closed is None else g_closed
    return RobotModel(
        name=robot.name or urdf_path.stem,
        urdf_path=urdf_path,
        link_names=order,
        joints=specs,
        joint_names=joint_names,
        lower=np.array(lower, dtype=np.float64),
        upper=np.array(upper, dtype=np.float64),
        ee_link=ee_link,
        ee_offset=np.eye(4) if ee_offset is None else ee_offset,
        visual_meshes=visual,
        collision_meshes=collision,
        link_colors=colors,
        gripper_joint=gripper_joint,
        gripper_open=0.0 if g_open is None else float(g_open),
        gripper_closed=0.0 if g_closed is None else float(g_closed),
        contact_links=tuple(contact_links),
        home_q=home_q,
    )
