"""Linear blend skinning of Gaussians on spring-mass particles (bones = particles), plus a rigid variant.

Binding (once): each Gaussian takes its k = 16 nearest rest particles with normalised inverse-distance
weights; each particle (bone) takes its k_bone = 8 nearest other particles as its fitting neighbourhood.
Per frame: bone rotation R_b = polar(sum_j (p_j - p_b)(p0_j - p0_b)^T + eps tr() I) (Procrustes by SVD,
reflection fixed; the tiny eps picks the least rotation when a neighbourhood is degenerate, e.g. a
straight rope), x' = sum_k w_k (R_k (x - b_k) + b_k + t_k) with t_k = p_k - b_k, and the Gaussian
rotation is pre-multiplied by the polar rotation of sum_k w_k R_k.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import warp as wp

from twinbench.gaussians.cloud import DeviceGaussians, GaussianCloud
from twinbench.gaussians.sh import sh_degree, sh_rotation_matrices
from twinbench.gaussians.threads import default_threads, launch_split

_EPS_REL = 1e-5
# posing splits over the threads from this many Gaussians (below, one thread is faster: a hand-off to
# another thread costs 0.1-0.3 ms on a 2-core KVM host; a rigid pose ~20 ns a Gaussian, LBS ~110)
_SPLIT_RIGID = 40_000
_RIGID_CHUNK = 32  # Gaussians a CPU thread of the rigid poser takes in turn
_SPLIT_SKIN = 10_000

wp.set_module_options({"enable_backward": False})


@dataclass
class SkinBinding:
    """Host arrays fixed at bind time."""

    indices: np.ndarray  # (N, k) int32 bone ids per Gaussian
    weights: np.ndarray  # (N, k) float32, rows sum to 1
    bone_neighbors: np.ndarray  # (P, k_bone) int32
    rest_particles: np.ndarray  # (P, 3) float32


def bind(gaussian_means, particles, k: int = 16, k_bone: int = 8, device: str | None = None) -> SkinBinding:
    """Bind Gaussians (N, 3) to rest particles (P, 3). `device` is accepted for symmetry (binding is host)."""
    from scipy.spatial import cKDTree

    means = np.asarray(gaussian_means, dtype=np.float64)
    parts = np.asarray(particles, dtype=np.float64)
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"bind: gaussian_means must be (N, 3), got {means.shape}")
    if parts.ndim != 2 or parts.shape[1] != 3:
        raise ValueError(f"bind: particles must be (P, 3), got {parts.shape}")
    if not (np.all(np.isfinite(means)) and np.all(np.isfinite(parts))):
        raise ValueError("bind: gaussian_means and particles must be finite (found NaN/inf)")
    p = len(parts)
    if p < 2:
        raise ValueError(f"bind: need at least 2 particles, got {p}")
    k = min(k, p)
    k_bone = min(k_bone, p - 1)
    tree = cKDTree(parts)
    dist, idx = tree.query(means, k=k)
    dist, idx = dist.reshape(len(means), k), idx.reshape(len(means), k)
    inv = 1.0 / np.maximum(dist, 1e-9)
    weights = inv / inv.sum(axis=1, keepdims=True)
    _, nbr = tree.query(parts, k=k_bone + 1)
    nbr = nbr.reshape(p, k_bone + 1)
    # drop each particle itself (normally column 0; duplicates may reorder)
    self_col = np.argmax(nbr == np.arange(p)[:, None], axis=1)
    has_self = np.any(nbr == np.arange(p)[:, None], axis=1)
    self_col = np.where(has_self, self_col, k_bone)
    mask = np.ones_like(nbr, dtype=bool)
    mask[np.arange(p), self_col] = False
    bone_nbr = nbr[mask].reshape(p, k_bone)
    return SkinBinding(
        idx.astype(np.int32), weights.astype(np.float32), bone_nbr.astype(np.int32), parts.astype(np.float32)
    )


@wp.func
def _frob2(m: wp.mat33):
    return wp.ddot(m, m)


@wp.func
def _polar_rotation(a: wp.mat33):
    """Rotation factor of the polar decomposition (nearest rotation to `a`).

    det(a) > 0: scaled Newton iteration X <- (g X + X^-T / g) / 2 (accurate to float32 round-off, also for
    nearly symmetric inputs where a float32 SVD is not); otherwise SVD with the reflection fixed."""
    if wp.determinant(a) > 0.0:
        x = a
        for _it in range(30):
            xi = wp.inverse(x)
            g = wp.sqrt(wp.sqrt(_frob2(xi) / _frob2(x)))
            xn = 0.5 * (g * x + wp.transpose(xi) / g)
            diff = _frob2(xn - x)
            x = xn
            if diff < 1.0e-12:
                break
        return x
    u = wp.mat33()
    s = wp.vec3()
    v = wp.mat33()
    wp.svd3(a, u, s, v)
    r = u * wp.transpose(v)
    if wp.determinant(r) < 0.0:
        u = wp.mat33(u[0, 0], u[0, 1], -u[0, 2], u[1, 0], u[1, 1], -u[1, 2], u[2, 0], u[2, 1], -u[2, 2])
        r = u * wp.transpose(v)
    return r


@wp.func
def _rotate_quat_wxyz(r: wp.mat33, q: wp.vec4):
    """wxyz quaternion of rotation r applied after the rotation of q (wxyz); Warp's quat is xyzw."""
    qn = wp.quat_from_matrix(r) * wp.quat(q[1], q[2], q[3], q[0])
    return wp.vec4(qn[3], qn[0], qn[1], qn[2])


@wp.kernel
def _bone_rotations(
    rest: wp.array(dtype=wp.vec3),
    cur: wp.array(dtype=wp.vec3),
    cur_starts: wp.array(dtype=int),
    nbrs: wp.array2d(dtype=wp.int32),
    eps_rel: float,
    rots: wp.array(dtype=wp.mat33),
):
    """Bone b of copy c (thread c * P + b) from the particles cur[cur_starts[c]:]."""
    i = wp.tid()
    num = rest.shape[0]
    c = i // num
    b = i - c * num
    base = cur_starts[c]
    a = wp.mat33()
    p0 = rest[b]
    p1 = cur[base + b]
    tr = float(0.0)  # noqa: UP018 (a Warp dynamic variable)
    for j in range(nbrs.shape[1]):
        n = nbrs[b, j]
        d0 = rest[n] - p0
        d1 = cur[base + n] - p1
        a += wp.outer(d1, d0)
        tr += wp.length(d1) * wp.length(d0)
    rots[i] = _polar_rotation(a + wp.identity(3, dtype=float) * (eps_rel * tr))


@wp.kernel
def _skin(
    rest_means: wp.array(dtype=wp.vec3),
    rest_quats: wp.array(dtype=wp.vec4),
    indices: wp.array2d(dtype=wp.int32),
    weights: wp.array2d(dtype=wp.float32),
    rest: wp.array(dtype=wp.vec3),
    cur: wp.array(dtype=wp.vec3),
    cur_starts: wp.array(dtype=int),
    rots: wp.array(dtype=wp.mat33),
    out_starts: wp.array(dtype=int),
    start: int,
    out_means: wp.array(dtype=wp.vec3),
    out_quats: wp.array(dtype=wp.vec4),
):
    """Gaussian g of copy c (thread start + t = c * N + g) into out_*[out_starts[c] + g]."""
    i = wp.tid() + start
    num = rest_means.shape[0]
    c = i // num
    g = i - c * num
    base = cur_starts[c]
    first_bone = c * rest.shape[0]
    x = rest_means[g]
    xn = wp.vec3()
    m = wp.mat33()
    for j in range(indices.shape[1]):
        b = indices[g, j]
        w = weights[g, j]
        r = rots[first_bone + b]
        xn += w * (r * (x - rest[b]) + cur[base + b])
        m += w * r
    o = out_starts[c] + g
    out_means[o] = xn
    out_quats[o] = _rotate_quat_wxyz(_polar_rotation(m), rest_quats[g])


@wp.kernel
def _label_quats(rots: wp.array(dtype=wp.mat33), out: wp.array(dtype=wp.quat)):
    """Each label's rotation as a quaternion (xyzw), once per pose rather than once per Gaussian."""
    k = wp.tid()
    out[k] = wp.quat_from_matrix(rots[k])


@wp.kernel
def _rigid_by_label(
    rest_means: wp.array(dtype=wp.vec3),
    rest_quats: wp.array(dtype=wp.vec4),
    rest_sh: wp.array2d(dtype=wp.vec3),
    labels: wp.array(dtype=wp.int32),
    num_labels: int,
    rots: wp.array(dtype=wp.mat33),
    rot_quats: wp.array(dtype=wp.quat),
    trans: wp.array(dtype=wp.vec3),
    sh_mats: wp.array2d(dtype=wp.float32),
    out_starts: wp.array(dtype=int),
    chunk: int,
    start: int,
    out_means: wp.array(dtype=wp.vec3),
    out_quats: wp.array(dtype=wp.vec4),
    out_sh: wp.array2d(dtype=wp.vec3),
):
    """Chunk t of copy c (thread start + tid = c * ceil(N / chunk) + t): its Gaussians i moved by the copy's
    transform of their label (`rot_quats`: the rotations as quaternions, `_label_quats`), into
    out_*[out_starts[c] + i]. A thread takes `chunk` Gaussians (on CPU a thread each cost more than the
    transform)."""
    num = rest_means.shape[0]
    per_copy = (num + chunk - 1) // chunk
    t = wp.tid() + start
    c = t // per_copy
    i0 = (t - c * per_copy) * chunk
    base = out_starts[c]
    k = rest_sh.shape[1]
    for i in range(i0, wp.min(i0 + chunk, num)):
        lab = c * num_labels + labels[i]
        o = base + i
        out_means[o] = rots[lab] * rest_means[i] + trans[lab]
        q = rest_quats[i]
        qn = rot_quats[lab] * wp.quat(q[1], q[2], q[3], q[0])  # as _rotate_quat_wxyz, the same floats
        out_quats[o] = wp.vec4(qn[3], qn[0], qn[1], qn[2])
        out_sh[o, 0] = rest_sh[i, 0]
        # band l occupies coefficients l^2 .. (l+1)^2 - 1; its (2l+1)^2 matrix entries follow the previous
        # bands'
        moff = int(0)  # noqa: UP018 (a Warp dynamic variable)
        band = int(1)  # noqa: UP018
        while band * band < k:
            size = 2 * band + 1
            first = band * band
            for a in range(size):
                acc = wp.vec3()
                for b in range(size):
                    acc += sh_mats[lab, moff + a * size + b] * rest_sh[i, first + b]
                out_sh[o, first + a] = acc
            moff += size * size
            band += 1


def _upload(dst: wp.array, values: np.ndarray) -> None:
    """Host values into a float32 Warp array of the same shape (on CPU written in place, no temporary)."""
    if dst.device.is_cpu:
        view = dst.numpy()
        view[...] = values.reshape(view.shape)
    else:
        dst.assign(np.ascontiguousarray(values, dtype=np.float32))


def _starts(starts, count: int, what: int, device) -> wp.array:
    """Checked first indices of `len(starts)` copies of `count` items in an array of `what` items, as a
    device array (cached: a twin passes the same starts every step)."""
    s = np.asarray(starts)
    if s.ndim != 1 or not s.size or not np.issubdtype(s.dtype, np.integer):
        raise ValueError(f"starts must be a non-empty 1-D sequence of integers, got {starts!r}")
    if s.min() < 0 or s.max() + count > what:
        raise ValueError(f"starts: every copy of {count} items must fit in the {what} items of the output")
    return _index_array(tuple(int(i) for i in s), str(device))


@functools.lru_cache(maxsize=64)
def _index_array(values: tuple[int, ...], device: str) -> wp.array:
    return wp.array(np.array(values, np.int32), dtype=int, device=device)


class LabelRigidPoser:
    """Per-label rigid motion on the device (e.g. robot links): Gaussian i follows transforms[labels[i]],
    a 4x4 pose relative to the rest pose; means, quats and the SH bands (exact per-label rotation
    matrices, computed on the host) are updated in one launch. `update` returns a DeviceGaussians that
    shares scales and opacities with the rest cloud."""

    def __init__(
        self,
        rest: GaussianCloud | DeviceGaussians,
        labels,
        num_labels: int | None = None,
        device: str = "cpu",
        out: DeviceGaussians | None = None,
    ) -> None:
        """`out` (optional): where `update` writes means, quats and SH, e.g. views of a scene-wide buffer
        (its SH may have more coefficients than `rest`: the extra ones are left as they are)."""
        rest_dev = rest if isinstance(rest, DeviceGaussians) else rest.to_device(device)
        self.device = rest_dev.device
        lab = np.asarray(labels)
        n = len(rest_dev)
        if lab.shape != (n,) or (lab.size and not np.issubdtype(lab.dtype, np.integer)):
            raise ValueError(f"LabelRigidPoser: labels must be ({n},) integers, got {lab.shape} {lab.dtype}")
        self.num_labels = int(lab.max()) + 1 if num_labels is None and lab.size else int(num_labels or 0)
        if lab.size and (lab.min() < 0 or lab.max() >= self.num_labels):
            raise ValueError(f"LabelRigidPoser: labels must lie in [0, {self.num_labels})")
        self.rest = rest_dev
        self.degree = sh_degree(rest_dev.sh.shape[1])
        self._labels = wp.array(lab.astype(np.int32), dtype=wp.int32, device=self.device)
        if out is None:
            out = DeviceGaussians(
                means=wp.empty(n, dtype=wp.vec3, device=self.device),
                quats=wp.empty(n, dtype=wp.vec4, device=self.device),
                scales=rest_dev.scales,
                opacities=rest_dev.opacities,
                sh=wp.empty(rest_dev.sh.shape, dtype=wp.vec3, device=self.device),
            )
        self.posed = self._check_out(out)
        width = max(1, sum((2 * b + 1) ** 2 for b in range(1, self.degree + 1)))
        self._rots = wp.empty(self.num_labels, dtype=wp.mat33, device=self.device)
        self._rot_quats = wp.empty(self.num_labels, dtype=wp.quat, device=self.device)
        self._trans = wp.empty(self.num_labels, dtype=wp.vec3, device=self.device)
        self._sh_mats = wp.zeros((self.num_labels, width), dtype=wp.float32, device=self.device)

    def _check_out(self, out: DeviceGaussians, exact: bool = True) -> DeviceGaussians:
        """`out` on this device with >= the rest cloud's SH coefficients, and (`exact`) its size."""
        n, k = len(self.rest), self.rest.sh.shape[1]
        if (exact and len(out) != n) or out.sh.shape[1] < k or out.device != self.device:
            raise ValueError(
                f"LabelRigidPoser: out must hold {n if exact else 'the'} Gaussians with >= {k} SH "
                f"coefficients on {self.device}, got {len(out)} with {out.sh.shape[1]} on {out.device}"
            )
        return out

    def update(self, transforms, out: DeviceGaussians | None = None) -> DeviceGaussians:
        """Pose with `transforms` (num_labels, 4, 4), each a rigid transform from the rest pose, into
        `out` (same requirements as the constructor's) or the poser's own output."""
        target = self.posed if out is None else self._check_out(out)
        self.update_many(np.asarray(transforms, dtype=np.float64)[None], target, [0])
        return target

    def update_many(self, transforms, out: DeviceGaussians, starts) -> DeviceGaussians:
        """Pose several copies in one launch (e.g. one per world of a scene buffer): copy c with
        `transforms[c]` (C, num_labels, 4, 4) into `out` from index `starts[c]`. Each copy equals
        `update(transforms[c])`."""
        t = np.asarray(transforms, dtype=np.float64)
        copies = t.shape[0] if t.ndim == 4 else 0
        if t.shape != (copies, self.num_labels, 4, 4) or not copies or not np.all(np.isfinite(t)):
            raise ValueError(
                f"LabelRigidPoser.update: transforms must be finite (copies, {self.num_labels}, 4, 4), "
                f"got {t.shape}"
            )
        rots = t[..., :3, :3].reshape(-1, 3, 3)
        ortho = np.abs(rots @ rots.transpose(0, 2, 1) - np.eye(3)) <= 1e-5 + 1e-5 * np.eye(3)  # np.allclose's
        if not ortho.all() or np.any(np.linalg.det(rots) < 0):
            raise ValueError("LabelRigidPoser.update: every transform's 3x3 block must be a rotation")
        n = len(self.rest)
        self._check_out(out, exact=False)
        first = _starts(starts, n, len(out), self.device)
        if first.shape[0] != copies:
            raise ValueError(f"LabelRigidPoser.update: {copies} transforms sets but {first.shape[0]} starts")
        if self._rots.shape[0] != rots.shape[0]:
            self._rots = wp.empty(rots.shape[0], dtype=wp.mat33, device=self.device)
            self._rot_quats = wp.empty(rots.shape[0], dtype=wp.quat, device=self.device)
            self._trans = wp.empty(rots.shape[0], dtype=wp.vec3, device=self.device)
            self._sh_mats = wp.zeros((rots.shape[0], self._sh_mats.shape[1]), dtype=wp.float32,
                                     device=self.device)
        _upload(self._rots, rots)
        _upload(self._trans, t[..., :3, 3].reshape(-1, 3))
        if self.degree > 0:
            mats = np.stack([
                np.concatenate([m.ravel() for m in sh_rotation_matrices(r, self.degree)[1:]]) for r in rots
            ])
            _upload(self._sh_mats, mats)
        wp.launch(_label_quats, dim=rots.shape[0], inputs=[self._rots], outputs=[self._rot_quats],
                  device=self.device)
        chunk = _RIGID_CHUNK if self.device.is_cpu else 1
        inputs = [self.rest.means, self.rest.quats, self.rest.sh, self._labels, self.num_labels, self._rots,
                  self._rot_quats, self._trans, self._sh_mats, first, chunk]  # fmt: skip
        threads = default_threads() if copies * n >= _SPLIT_RIGID else 1
        outputs = [out.means, out.quats, out.sh]
        chunks = copies * ((n + chunk - 1) // chunk)
        launch_split(_rigid_by_label, chunks, inputs, outputs, self.device, threads)
        return out


class LBSSkinner:
    """Device-resident LBS: holds the binding and rest Gaussians; `update(particles)` fills `means`
    (vec3) and `quats` (vec4 wxyz) on the device and returns them."""

    def __init__(self, binding: SkinBinding, rest_means, rest_quats, device: str = "cpu") -> None:
        rest_means = np.asarray(rest_means, dtype=np.float32)
        rest_quats = np.asarray(rest_quats, dtype=np.float32)
        n = binding.indices.shape[0]
        if rest_means.shape != (n, 3) or rest_quats.shape != (n, 4):
            raise ValueError(
                f"LBSSkinner: rest_means/rest_quats must be ({n}, 3)/({n}, 4) to match the binding, "
                f"got {rest_means.shape}/{rest_quats.shape}"
            )
        self.device = wp.get_device(device)
        self.num_particles = binding.rest_particles.shape[0]
        self._indices = wp.array(binding.indices, dtype=wp.int32, device=device)
        self._weights = wp.array(binding.weights, dtype=wp.float32, device=device)
        self._nbrs = wp.array(binding.bone_neighbors, dtype=wp.int32, device=device)
        self._rest = wp.array(binding.rest_particles, dtype=wp.vec3, device=device)
        self._rest_means = wp.array(rest_means, dtype=wp.vec3, device=device)
        self._rest_quats = wp.array(rest_quats, dtype=wp.vec4, device=device)
        self.bone_rotations = wp.zeros(self.num_particles, dtype=wp.mat33, device=device)
        self.means = wp.zeros(n, dtype=wp.vec3, device=device)
        self.quats = wp.zeros(n, dtype=wp.vec4, device=device)

    def update(
        self, particles, out_means: wp.array | None = None, out_quats: wp.array | None = None
    ) -> tuple[wp.array, wp.array]:
        """Skin to current particle positions ((P, 3) numpy or a vec3 wp.array on this device).

        Results go to `out_means` / `out_quats` when given (e.g. slices of a scene-wide DeviceGaussians),
        else to this skinner's own `means` / `quats`; returns the arrays written."""
        if not isinstance(particles, wp.array):
            arr = np.asarray(particles, dtype=np.float32)
            if arr.shape != (self.num_particles, 3):
                raise ValueError(
                    f"LBSSkinner.update: particles must be ({self.num_particles}, 3), got {arr.shape}"
                )
            if not np.all(np.isfinite(arr)):
                raise ValueError("LBSSkinner.update: particles contain NaN/inf")
            particles = wp.array(arr, dtype=wp.vec3, device=self.device)
        elif particles.shape[0] != self.num_particles:
            raise ValueError(
                f"LBSSkinner.update: expected {self.num_particles} particles, got {particles.shape[0]}"
            )
        means = self.means if out_means is None else out_means
        quats = self.quats if out_quats is None else out_quats
        n = self.means.shape[0]
        if means.shape[0] != n or quats.shape[0] != n:
            raise ValueError(f"LBSSkinner.update: out_means/out_quats must hold {n} entries")
        return self.update_many(particles, [0], means, quats, [0])

    def update_many(
        self, particles: wp.array, particle_starts, out_means: wp.array, out_quats: wp.array, out_starts
    ) -> tuple[wp.array, wp.array]:
        """Skin several copies in one launch per stage (e.g. one per world): copy c to the particles
        `particles[particle_starts[c]:]` (a vec3 wp.array on this device) into `out_means` / `out_quats`
        from index `out_starts[c]`. Each copy equals `update` on its particles."""
        if not isinstance(particles, wp.array) or particles.device != self.device:
            raise ValueError(f"LBSSkinner.update_many: particles must be a vec3 wp.array on {self.device}")
        n, p = self.means.shape[0], self.num_particles
        cur = _starts(particle_starts, p, particles.shape[0], self.device)
        out = _starts(out_starts, n, min(out_means.shape[0], out_quats.shape[0]), self.device)
        copies = cur.shape[0]
        if out.shape[0] != copies:
            raise ValueError(
                f"LBSSkinner.update_many: {copies} particle starts but {out.shape[0]} output starts"
            )
        if self.bone_rotations.shape[0] != copies * p:
            self.bone_rotations = wp.zeros(copies * p, dtype=wp.mat33, device=self.device)
        wp.launch(
            _bone_rotations,
            dim=copies * p,
            inputs=[self._rest, particles, cur, self._nbrs, _EPS_REL],
            outputs=[self.bone_rotations],
            device=self.device,
        )
        inputs = [self._rest_means, self._rest_quats, self._indices, self._weights, self._rest, particles,
                  cur, self.bone_rotations, out]  # fmt: skip
        threads = default_threads() if copies * n >= _SPLIT_SKIN else 1
        launch_split(_skin, copies * n, inputs, [out_means, out_quats], self.device, threads)
        return out_means, out_quats


def skin(binding: SkinBinding, rest_cloud: GaussianCloud, particles, device: str = "cpu") -> GaussianCloud:
    """Host convenience: a new GaussianCloud with LBS-deformed means and quats (SH, scales, opacity kept;
    view-dependent SH bands are not rotated)."""
    sk = LBSSkinner(binding, rest_cloud.means, rest_cloud.quats, device=device)
    means, quats = sk.update(particles)
    return GaussianCloud(
        means.numpy(),
        quats.numpy(),
        rest_cloud.log_scales.copy(),
        rest_cloud.logit_opacities.copy(),
        rest_cloud.sh.copy(),
    )
