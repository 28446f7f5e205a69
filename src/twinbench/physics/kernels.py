"""Warp kernels of the spring-mass solver (same code on ``cpu`` and ``cuda``).

The arithmetic follows PhysTwin's ``SpringMassSystemWarp`` expression by expression (see the golden
README in ``shared/reference/phystwin``) so that float32 results match the reference trajectories.
Spring indices ``>= n`` refer to kinematic control point ``idx - n``.
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": True})


@wp.func
def end_position(
    x: wp.array(dtype=wp.vec3),
    ctrl_from: wp.array(dtype=wp.vec3),
    ctrl_to: wp.array(dtype=wp.vec3),
    t: float,
    idx: int,
    n: int,
):
    if idx < n:
        return x[idx]
    c = idx - n
    a = ctrl_from[c]
    return a + (ctrl_to[c] - a) * t


@wp.func
def end_velocity(v: wp.array(dtype=wp.vec3), idx: int, n: int):
    # Control points carry zero velocity (PhysTwin never writes it).
    if idx < n:
        return v[idx]
    return wp.vec3(0.0, 0.0, 0.0)


@wp.func
def spring_force_between(
    x1: wp.vec3, x2: wp.vec3, v1: wp.vec3, v2: wp.vec3, rest: float, y: float, dashpot: float
):
    """Spring + dashpot force on the first end (PhysTwin's expressions)."""
    dis = x2 - x1
    dis_len = wp.length(dis)
    d = dis / wp.max(dis_len, 1e-6)
    elastic = y * (dis_len / rest - 1.0) * d
    v_rel = wp.dot(v2 - v1, d)
    damp = dashpot * v_rel * d
    return elastic + damp


@wp.kernel
def effective_stiffness(
    log_y: wp.array(dtype=float),
    rest_lengths: wp.array(dtype=float),
    y_min: float,
    y_max: float,
    ry: wp.array(dtype=wp.vec2),
):
    """Per spring (rest length, clamp(exp(log Y))), the stiffness -1 for an inactive spring
    (exp(log Y) <= y_min)."""
    s = wp.tid()
    e = wp.exp(log_y[s])
    y = -1.0
    if e > y_min:
        y = wp.clamp(e, y_min, y_max)
    ry[s] = wp.vec2(rest_lengths[s], y)


@wp.func
def spring_of(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    e: wp.vec2i,
    r: wp.vec2,
    dashpot: float,
    ctrl_from: wp.array(dtype=wp.vec3),
    ctrl_to: wp.array(dtype=wp.vec3),
    t: float,
    n: int,
):
    """Force on the first end of the spring with ends `e` and (rest length, stiffness) `r` (0 if inactive)."""
    f = wp.vec3(0.0, 0.0, 0.0)
    if r[1] >= 0.0:
        f = spring_force_between(
            end_position(x, ctrl_from, ctrl_to, t, e[0], n), end_position(x, ctrl_from, ctrl_to, t, e[1], n),
            end_velocity(v, e[0], n), end_velocity(v, e[1], n), r[0], r[1], dashpot,
        )
    return f


@wp.kernel
def eval_spring_forces(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    springs: wp.array(dtype=wp.vec2i),
    ry: wp.array(dtype=wp.vec2),
    dashpot: float,
    ctrl_from: wp.array(dtype=wp.vec3),
    ctrl_to: wp.array(dtype=wp.vec3),
    t: float,
    n: int,
    out: wp.array(dtype=wp.vec3),
):
    """Per-spring force on the first end (the second end gets its negative), for the per-particle gather."""
    s = wp.tid()
    out[s] = spring_of(x, v, springs[s], ry[s], dashpot, ctrl_from, ctrl_to, t, n)


# CPU only: object springs [first, first + count) (or listed[first + k], ascending) added to both their
# ends in spring order. A spring's force is a chain of a dependent square root and divisions: one spring at a
# time leaves the core waiting on that chain. So each batch of 64 springs is computed 8 springs per SIMD
# instruction with `spring_force_between`'s expressions in the same order (IEEE lane-wise, no contraction:
# the same floats), then added to the ends one spring after another, the first end's sum held in a register
# while consecutive springs share it. The gather loads each end's position and velocity as one 16-byte row
# (x, y, z and the next float, unused), takes the 8 springs' differences row by row and transposes them
# (8x8, shuffles) into one vector per component: about a third of the scalar loads and stores of a gather
# component by component. A 16-byte row read past the last particle's 12 bytes would leave the array, so a
# group of 8 springs touching the last particle reads it from a padded copy. (Loops stay scalar where the
# compiler would use gather instructions, slower than loads on current x86.) Raw element pointers: the
# arrays must be contiguous (the solver's and model's own arrays are).
_SCATTER_OBJECT_SPRINGS_CPU = r"""
#if !defined(__CUDA_ARCH__)
{
_Pragma("clang fp contract(off)")  // no fused multiply-adds: Warp's per-spring expressions round each step
typedef float f8 __attribute__((ext_vector_type(8)));
typedef float f4 __attribute__((ext_vector_type(4)));
constexpr int B = 64;
const float* X = (const float*)x.data;
const float* V = (const float*)v.data;
const wp::vec2i* S = (const wp::vec2i*)springs.data;
const wp::vec2* R = (const wp::vec2*)ry.data;
const int* L = listed.shape[0] > 0 ? (const int*)listed.data : nullptr;
wp::vec3* F = (wp::vec3*)f.data;
const int last = (x.shape[0] < v.shape[0] ? x.shape[0] : v.shape[0]) - 1;
alignas(16) const float xl[4] = {X[3 * last], X[3 * last + 1], X[3 * last + 2], 0.0f};
alignas(16) const float vl[4] = {V[3 * last], V[3 * last + 1], V[3 * last + 2], 0.0f};
alignas(32) float out[3][B];
int a[B], b[B];
for (int k = 0; k < count; k += B) {
    const int m = count - k < B ? count - k : B;
    for (int j = 0; j < B; j += 8) {
        alignas(32) float rr[8], yy[8];
        bool padded = false;  // a spring of the group touches the last particle
        _Pragma("clang loop vectorize(disable) interleave(disable) unroll(full)")
        for (int i = 0; i < 8; ++i) {
            int s = first + k + (j + i < m ? j + i : m - 1);
            if (L) s = L[s];
            const wp::vec2i e = S[s];
            const wp::vec2 r = R[s];
            a[j + i] = e[0]; b[j + i] = e[1];
            rr[i] = r[0]; yy[i] = r[1];
            padded |= (e[0] == last) | (e[1] == last);
        }
        f8 d[8];  // per spring: x2 - x1 in lanes 0-2, v2 - v1 in lanes 4-6
        if (!padded) {
            _Pragma("clang loop vectorize(disable) interleave(disable) unroll(full)")
            for (int i = 0; i < 8; ++i) {
                f4 x1, x2, v1, v2;
                __builtin_memcpy(&x1, X + 3 * a[j + i], 16); __builtin_memcpy(&x2, X + 3 * b[j + i], 16);
                __builtin_memcpy(&v1, V + 3 * a[j + i], 16); __builtin_memcpy(&v2, V + 3 * b[j + i], 16);
                d[i] = __builtin_shufflevector(x2 - x1, v2 - v1, 0, 1, 2, 3, 4, 5, 6, 7);
            }
        } else {
            for (int i = 0; i < 8; ++i) {
                const int p = a[j + i], q = b[j + i];
                f4 x1, x2, v1, v2;
                __builtin_memcpy(&x1, p == last ? xl : X + 3 * p, 16);
                __builtin_memcpy(&x2, q == last ? xl : X + 3 * q, 16);
                __builtin_memcpy(&v1, p == last ? vl : V + 3 * p, 16);
                __builtin_memcpy(&v2, q == last ? vl : V + 3 * q, 16);
                d[i] = __builtin_shufflevector(x2 - x1, v2 - v1, 0, 1, 2, 3, 4, 5, 6, 7);
            }
        }
        // the 8x8 transpose of d, its rows 0-2 and 4-6 only
        const f8 t0 = __builtin_shufflevector(d[0], d[1], 0, 8, 1, 9, 4, 12, 5, 13);
        const f8 t1 = __builtin_shufflevector(d[0], d[1], 2, 10, 3, 11, 6, 14, 7, 15);
        const f8 t2 = __builtin_shufflevector(d[2], d[3], 0, 8, 1, 9, 4, 12, 5, 13);
        const f8 t3 = __builtin_shufflevector(d[2], d[3], 2, 10, 3, 11, 6, 14, 7, 15);
        const f8 t4 = __builtin_shufflevector(d[4], d[5], 0, 8, 1, 9, 4, 12, 5, 13);
        const f8 t5 = __builtin_shufflevector(d[4], d[5], 2, 10, 3, 11, 6, 14, 7, 15);
        const f8 t6 = __builtin_shufflevector(d[6], d[7], 0, 8, 1, 9, 4, 12, 5, 13);
        const f8 t7 = __builtin_shufflevector(d[6], d[7], 2, 10, 3, 11, 6, 14, 7, 15);
        const f8 u0 = __builtin_shufflevector(t0, t2, 0, 1, 8, 9, 4, 5, 12, 13);
        const f8 u1 = __builtin_shufflevector(t0, t2, 2, 3, 10, 11, 6, 7, 14, 15);
        const f8 u2 = __builtin_shufflevector(t1, t3, 0, 1, 8, 9, 4, 5, 12, 13);
        const f8 u4 = __builtin_shufflevector(t4, t6, 0, 1, 8, 9, 4, 5, 12, 13);
        const f8 u5 = __builtin_shufflevector(t4, t6, 2, 3, 10, 11, 6, 7, 14, 15);
        const f8 u6 = __builtin_shufflevector(t5, t7, 0, 1, 8, 9, 4, 5, 12, 13);
        const f8 dx = __builtin_shufflevector(u0, u4, 0, 1, 2, 3, 8, 9, 10, 11);
        const f8 wx = __builtin_shufflevector(u0, u4, 4, 5, 6, 7, 12, 13, 14, 15);
        const f8 dy = __builtin_shufflevector(u1, u5, 0, 1, 2, 3, 8, 9, 10, 11);
        const f8 wy = __builtin_shufflevector(u1, u5, 4, 5, 6, 7, 12, 13, 14, 15);
        const f8 dz = __builtin_shufflevector(u2, u6, 0, 1, 2, 3, 8, 9, 10, 11);
        const f8 wz = __builtin_shufflevector(u2, u6, 4, 5, 6, 7, 12, 13, 14, 15);
        f8 rest, y;
        __builtin_memcpy(&rest, rr, 32); __builtin_memcpy(&y, yy, 32);
        const f8 len = __builtin_elementwise_sqrt(dx * dx + dy * dy + dz * dz);
        const f8 eps = 1e-6f, zero = 0.0f;
        const f8 norm = len >= eps ? len : eps;
        const f8 ux = dx / norm, uy = dy / norm, uz = dz / norm;
        const f8 elastic = y * (len / rest - 1.0f);
        const f8 damp = dashpot * (wx * ux + wy * uy + wz * uz);
        const f8 fx = y >= zero ? elastic * ux + damp * ux : zero;
        const f8 fy = y >= zero ? elastic * uy + damp * uy : zero;
        const f8 fz = y >= zero ? elastic * uz + damp * uz : zero;
        __builtin_memcpy(&out[0][j], &fx, 32); __builtin_memcpy(&out[1][j], &fy, 32);
        __builtin_memcpy(&out[2][j], &fz, 32);
    }
    int held = a[0];
    wp::vec3 sum = F[held];
    _Pragma("clang loop vectorize(disable) interleave(disable)")
    for (int j = 0; j < m; ++j) {
        const wp::vec3 fs(out[0][j], out[1][j], out[2][j]);
        if (a[j] != held) { F[held] = sum; held = a[j]; sum = F[held]; }
        sum = sum + fs;
        if (b[j] == held) sum = sum - fs;  // a spring from a particle to itself
        else F[b[j]] = F[b[j]] - fs;
    }
    F[held] = sum;
}
}
#endif
"""


@wp.func_native(_SCATTER_OBJECT_SPRINGS_CPU)
def _scatter_object_springs_cpu(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    springs: wp.array(dtype=wp.vec2i),
    ry: wp.array(dtype=wp.vec2),
    dashpot: float,
    first: int,
    count: int,
    listed: wp.array(dtype=int),
    f: wp.array(dtype=wp.vec3),
): ...


@wp.kernel(enable_backward=False)
def scatter_object_springs(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    springs: wp.array(dtype=wp.vec2i),
    ry: wp.array(dtype=wp.vec2),
    dashpot: float,
    first: int,
    count: int,
    listed: wp.array(dtype=int),
    f: wp.array(dtype=wp.vec3),
):
    """CPU only, one thread (dim=1): object springs `first + k` (or `listed[first + k]`, ascending),
    k < count, each added to both its ends in spring order (see _SCATTER_OBJECT_SPRINGS_CPU), so each
    particle's sum grows as in the per-particle gather, without a per-spring array (`f` must start at zero).
    Both ends are written: a part of a split frame owns `f` alone and reads only its own particles' sums (see
    `SpringMassSolver._zero_forces`)."""
    _scatter_object_springs_cpu(x, v, springs, ry, dashpot, first, count, listed, f)


@wp.kernel(enable_backward=False)
def scatter_control_springs(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    springs: wp.array(dtype=wp.vec2i),
    ry: wp.array(dtype=wp.vec2),
    dashpot: float,
    ctrl_from: wp.array(dtype=wp.vec3),
    ctrl_to: wp.array(dtype=wp.vec3),
    t: float,
    n: int,
    p0: int,
    p1: int,
    first: int,
    listed: wp.array(dtype=int),
    f: wp.array(dtype=wp.vec3),
):
    """CPU only: the scatter of `scatter_object_springs` for springs to control points (index >= n), one
    thread per spring, added only to their ends in [p0, p1)."""
    s = first + wp.tid()
    if listed.shape[0] > 0:
        s = listed[s]
    e = springs[s]
    fs = spring_of(x, v, e, ry[s], dashpot, ctrl_from, ctrl_to, t, n)
    if e[0] >= p0 and e[0] < p1:
        f[e[0]] = f[e[0]] + fs
    if e[1] >= p0 and e[1] < p1:
        f[e[1]] = f[e[1]] - fs


@wp.kernel(enable_backward=False)
def zero_forces(base: int, f: wp.array(dtype=wp.vec3)):
    f[base + wp.tid()] = wp.vec3(0.0, 0.0, 0.0)


@wp.kernel
def accumulate_spring_forces(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    springs: wp.array(dtype=wp.vec2i),
    rest_lengths: wp.array(dtype=float),
    log_y: wp.array(dtype=float),
    y_min: float,
    y_max: float,
    dashpot: float,
    ctrl_from: wp.array(dtype=wp.vec3),
    ctrl_to: wp.array(dtype=wp.vec3),
    t: float,
    n: int,
    f: wp.array(dtype=wp.vec3),
):
    """PhysTwin-style atomic accumulation (used on the differentiable path)."""
    s = wp.tid()
    e = wp.exp(log_y[s])
    if e > y_min:
        ends = springs[s]
        r = wp.vec2(rest_lengths[s], wp.clamp(e, y_min, y_max))
        fs = spring_of(x, v, ends, r, dashpot, ctrl_from, ctrl_to, t, n)
        i = ends[0]
        j = ends[1]
        if i < n:
            wp.atomic_add(f, i, fs)
        if j < n:
            wp.atomic_sub(f, j, fs)


@wp.func
def drag_factor_of(dt: float, drag: float):
    """Per-substep velocity factor of air drag (PhysTwin)."""
    return wp.exp(-dt * drag)


@wp.func
def velocity_update(v0: wp.vec3, f0: wp.vec3, m0: float, gravity: wp.vec3, dt: float, drag_factor: float):
    """PhysTwin's velocity step; `drag_factor` = `drag_factor_of(dt, drag)`."""
    all_force = f0 + m0 * gravity
    a = all_force / m0
    v1 = v0 + a * dt
    return v1 * drag_factor


@wp.func
def contact_velocity(vrel: wp.vec3, normal: wp.vec3, elas: float, fric: float):
    """PhysTwin contact law on a relative velocity approaching along -normal."""
    v_normal = wp.dot(vrel, normal) * normal
    v_tao = vrel - v_normal
    v_normal_length = wp.length(v_normal)
    v_tao_length = wp.max(wp.length(v_tao), 1e-6)
    e = wp.clamp(elas, 0.0, 1.0)
    mu = wp.clamp(fric, 0.0, 2.0)
    v_normal_new = -e * v_normal
    a = wp.max(0.0, 1.0 - mu * (1.0 + e) * v_normal_length / v_tao_length)
    return v_normal_new + a * v_tao


@wp.func
def mesh_contacts(
    xp: wp.vec3,
    vp: wp.vec3,
    mp: float,
    first: int,
    last: int,
    mesh_ids: wp.array(dtype=wp.uint64),
    mesh_elas: wp.array(dtype=float),
    mesh_fric: wp.array(dtype=float),
    face_offsets: wp.array(dtype=int),
    margin: float,
    dt: float,
    mesh_force: wp.array(dtype=wp.vec3),
    face_force: wp.array(dtype=wp.vec3),
    tid: int,
    per_particle: int,
    pm_force: wp.array(dtype=wp.vec3),
    pm_face: wp.array(dtype=int),
    pm_list: wp.array(dtype=int),
    pm_count: wp.array(dtype=int),
    mesh_lo: wp.array(dtype=wp.vec3),
    mesh_hi: wp.array(dtype=wp.vec3),
):
    """Velocity response against the triangle meshes ``[first, last)`` (the particle's world), relative
    to the mesh point velocity. The contact force is added to its mesh and face, or with ``per_particle``
    stored in the particle's own slot (``pm_force``/``pm_face``) and the slot appended to ``pm_list``
    (count in ``pm_count[0]``; particle order in a one-thread CPU loop) for `reduce_mesh_forces` to add
    in that order (so that two processes can share a frame). A particle
    outside a mesh's box ``[mesh_lo, mesh_hi]`` (the mesh over the whole frame, grown past the margin)
    is too far for a contact and skips the query."""
    v = vp
    for k in range(first, last):
        lo = mesh_lo[k]
        hi = mesh_hi[k]
        if xp[0] < lo[0] or xp[1] < lo[1] or xp[2] < lo[2] or xp[0] > hi[0] or xp[1] > hi[1] or xp[2] > hi[2]:
            continue
        mid = mesh_ids[k]
        q = wp.mesh_query_point_sign_normal(mid, xp, margin)
        if q.result:
            cp = wp.mesh_eval_position(mid, q.face, q.u, q.v)
            delta = xp - cp
            dist = wp.length(delta)
            normal = wp.mesh_eval_face_normal(mid, q.face)
            if dist > 1.0e-6:
                normal = delta / dist * q.sign
            vm = wp.mesh_eval_velocity(mid, q.face, q.u, q.v)
            vrel = v - vm
            if wp.dot(vrel, normal) < 0.0:
                v_new = vm + contact_velocity(vrel, normal, mesh_elas[k], mesh_fric[k])
                force = mp * (v_new - v) / dt
                if per_particle != 0:
                    slot = tid * (last - first) + k - first
                    pm_force[slot] = force
                    pm_face[slot] = q.face
                    pm_list[wp.atomic_add(pm_count, 0, 1)] = slot
                else:
                    wp.atomic_add(mesh_force, k, force)
                    wp.atomic_add(face_force, face_offsets[k] + q.face, force)
                v = v_new
    return v


@wp.func
def ground_integrate(x0: wp.vec3, v0: wp.vec3, elas: float, fric: float, dt: float, ground: int):
    """Ground plane z = 0 with time of impact, then the position update; returns (x_new, v_new)."""
    v1 = v0
    toi = float(0.0)  # noqa: UP018 (Warp needs a typed dynamic variable)
    if ground != 0:
        next_z = x0[2] + v0[2] * dt
        if next_z < 0.0 and v0[2] < -1.0e-4:
            v1 = contact_velocity(v0, wp.vec3(0.0, 0.0, 1.0), elas, fric)
            toi = -x0[2] / v0[2]
    return x0 + v0 * toi + v1 * (dt - toi), v1


@wp.struct
class ContactParams:
    mesh_ids: wp.array(dtype=wp.uint64)
    mesh_elas: wp.array(dtype=float)
    mesh_fric: wp.array(dtype=float)
    face_offsets: wp.array(dtype=int)
    margin: float
    mesh_force: wp.array(dtype=wp.vec3)
    face_force: wp.array(dtype=wp.vec3)
    particle_world: wp.array(dtype=int)
    world_mesh_start: wp.array(dtype=int)
    per_particle: int  # 1: contact forces go to pm_force/pm_face, their slots to pm_list (see mesh_contacts)
    pm_force: wp.array(dtype=wp.vec3)
    pm_face: wp.array(dtype=int)
    pm_list: wp.array(dtype=int)
    pm_count: wp.array(dtype=int)
    ground: int
    coeffs: wp.array(dtype=float)  # ground restitution, ground friction, object restitution, object friction
    mesh_lo: wp.array(dtype=wp.vec3)  # per mesh: a box holding it over the frame, grown past the margin
    mesh_hi: wp.array(dtype=wp.vec3)


@wp.func
def finish_particle(
    tid: int, x0: wp.vec3, v: wp.vec3, m: float, dt: float, cp: ContactParams,
    x_out: wp.array(dtype=wp.vec3), v_out: wp.array(dtype=wp.vec3),
):
    v1 = v
    if cp.mesh_ids.shape[0] > 0:
        w = cp.particle_world[tid]
        v1 = mesh_contacts(x0, v1, m, cp.world_mesh_start[w], cp.world_mesh_start[w + 1], cp.mesh_ids,
                           cp.mesh_elas, cp.mesh_fric, cp.face_offsets, cp.margin, dt, cp.mesh_force,
                           cp.face_force, tid, cp.per_particle, cp.pm_force, cp.pm_face, cp.pm_list,
                           cp.pm_count, cp.mesh_lo, cp.mesh_hi)
    xn, vn = ground_integrate(x0, v1, cp.coeffs[0], cp.coeffs[1], dt, cp.ground)
    x_out[tid] = xn
    v_out[tid] = vn


@wp.kernel
def particle_update(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    spring_f: wp.array(dtype=wp.vec3),
    inc_offsets: wp.array(dtype=int),
    inc_springs: wp.array(dtype=int),
    f_acc: wp.array(dtype=wp.vec3),
    use_gather: int,
    masses: wp.array(dtype=float),
    gravity: wp.vec3,
    dt: float,
    drag: float,
    finish: int,
    cp: ContactParams,
    base: int,
    v_star: wp.array(dtype=wp.vec3),
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
):
    """Spring forces (gathered from the incident springs in spring order, or read from ``f_acc``), gravity,
    drag; then contacts when ``finish`` (no particle-particle collision stage this substep). Thread i serves
    particle base + i. (CPU: `integrate_scattered`.)"""
    tid = base + wp.tid()
    f = wp.vec3(0.0, 0.0, 0.0)
    if use_gather != 0:
        for k in range(inc_offsets[tid], inc_offsets[tid + 1]):
            e = inc_springs[k]
            if e > 0:
                f = f + spring_f[e - 1]
            else:
                f = f - spring_f[-e - 1]
    else:
        f = f_acc[tid]
    m = masses[tid]
    vs = velocity_update(v[tid], f, m, gravity, dt, drag_factor_of(dt, drag))
    if finish != 0:
        finish_particle(tid, x[tid], vs, m, dt, cp, x_out, v_out)
    else:
        v_star[tid] = vs


@wp.kernel(enable_backward=False)
def compute_drag_factor(dt: float, drag: float, out: wp.array(dtype=float)):
    """One thread: `drag_factor_of(dt, drag)` (computed once for `integrate_scattered`)."""
    out[0] = drag_factor_of(dt, drag)


# CPU only: `velocity_update` of particles [p0, p1) into v_star, 8 particles per SIMD instruction: their 24
# force and velocity components read as three 8-float rows, masses and gravity repeated to match
# (m0 m0 m0 m1 ..., gx gy gz gx ...), the same IEEE operations in the same order (no contraction: the same
# floats), then the forces zeroed for the next substep's scatter. A particle's divisions by its mass were
# most of a one-thread loop's time.
_VELOCITIES_CPU = r"""
#if !defined(__CUDA_ARCH__)
{
_Pragma("clang fp contract(off)")
typedef float f8 __attribute__((ext_vector_type(8)));
const float* Fr = (const float*)f_acc.data;
float* Fw = (float*)f_acc.data;
const float* Vr = (const float*)v.data;
const float* M = (const float*)masses.data;
float* VS = (float*)v_star.data;
const float g[3] = {gravity[0], gravity[1], gravity[2]};
const f8 ga = {g[0], g[1], g[2], g[0], g[1], g[2], g[0], g[1]};
const f8 gb = {g[2], g[0], g[1], g[2], g[0], g[1], g[2], g[0]};
const f8 gc = {g[1], g[2], g[0], g[1], g[2], g[0], g[1], g[2]};
alignas(32) const float zeros[24] = {};
int i = p0;
for (; i + 8 <= p1; i += 8) {
    f8 m, f[3], w[3], out[3];
    __builtin_memcpy(&m, M + i, 32);
    const f8 ma = __builtin_shufflevector(m, m, 0, 0, 0, 1, 1, 1, 2, 2);
    const f8 mb = __builtin_shufflevector(m, m, 2, 3, 3, 3, 4, 4, 4, 5);
    const f8 mc = __builtin_shufflevector(m, m, 5, 5, 6, 6, 6, 7, 7, 7);
    __builtin_memcpy(f, Fr + 3 * i, 96);
    __builtin_memcpy(w, Vr + 3 * i, 96);
    out[0] = (w[0] + ((f[0] + ma * ga) / ma) * dt) * drag_factor;
    out[1] = (w[1] + ((f[1] + mb * gb) / mb) * dt) * drag_factor;
    out[2] = (w[2] + ((f[2] + mc * gc) / mc) * dt) * drag_factor;
    __builtin_memcpy(VS + 3 * i, out, 96);
    __builtin_memcpy(Fw + 3 * i, zeros, 96);
}
for (; i < p1; ++i) {
    const float m = M[i];
    for (int c = 0; c < 3; ++c) {
        VS[3 * i + c] = (Vr[3 * i + c] + ((Fr[3 * i + c] + m * g[c]) / m) * dt) * drag_factor;
        Fw[3 * i + c] = 0.0f;
    }
}
}
#endif
"""


@wp.func_native(_VELOCITIES_CPU)
def _velocities_cpu(
    v: wp.array(dtype=wp.vec3),
    f_acc: wp.array(dtype=wp.vec3),
    masses: wp.array(dtype=float),
    gravity: wp.vec3,
    dt: float,
    drag_factor: float,
    p0: int,
    p1: int,
    v_star: wp.array(dtype=wp.vec3),
): ...


# CPU only: `finish_particle` of particles [p0, p1) that have no collision candidate (with `candidates`:
# cand_count[i] == 0), are outside every mesh box of their world and do not reach the ground this substep
# (no contact: the position moves with v_star, ground_integrate's expression with toi = 0, the same floats);
# the others are listed in ascending order from pending[p0] on (-1 after the last) for the Warp code. A
# one-thread Warp loop spent most of its time reading the contact struct's arrays for particles far from
# any contact.
_FINISH_FREE_CPU = r"""
#if !defined(__CUDA_ARCH__)
{
_Pragma("clang fp contract(off)")
const wp::vec3* X = (const wp::vec3*)x.data;
const wp::vec3* VS = (const wp::vec3*)v_star.data;
const int* PW = (const int*)particle_world.data;
const int* WMS = (const int*)world_mesh_start.data;
const wp::vec3* LO = (const wp::vec3*)mesh_lo.data;
const wp::vec3* HI = (const wp::vec3*)mesh_hi.data;
wp::vec3* XO = (wp::vec3*)x_out.data;
wp::vec3* VO = (wp::vec3*)v_out.data;
int* P = (int*)pending.data;
const int* CC = (const int*)cand_count.data;
int c = p0;
for (int i = p0; i < p1; ++i) {
    const wp::vec3 xp = X[i], vp = VS[i];
    bool contact = candidates != 0 && CC[i] > 0;
    if (!contact && meshes > 0) {
        const int w = PW[i];
        for (int k = WMS[w]; k < WMS[w + 1]; ++k) {
            const wp::vec3 lo = LO[k], hi = HI[k];
            if (!(xp[0] < lo[0] || xp[1] < lo[1] || xp[2] < lo[2] || xp[0] > hi[0] || xp[1] > hi[1]
                  || xp[2] > hi[2])) { contact = true; break; }
        }
    }
    if (!contact && ground != 0) {
        const float next_z = xp[2] + vp[2] * dt;
        contact = next_z < 0.0f && vp[2] < -1.0e-4f;
    }
    if (contact) { P[c++] = i; continue; }
    const float toi = 0.0f;
    for (int d = 0; d < 3; ++d) XO[i][d] = xp[d] + vp[d] * toi + vp[d] * (dt - toi);
    VO[i] = vp;
}
if (c < p1) P[c] = -1;
}
#endif
"""


@wp.func_native(_FINISH_FREE_CPU)
def _finish_free_cpu(
    x: wp.array(dtype=wp.vec3),
    v_star: wp.array(dtype=wp.vec3),
    dt: float,
    candidates: int,
    cand_count: wp.array(dtype=int),
    meshes: int,
    particle_world: wp.array(dtype=int),
    world_mesh_start: wp.array(dtype=int),
    mesh_lo: wp.array(dtype=wp.vec3),
    mesh_hi: wp.array(dtype=wp.vec3),
    ground: int,
    p0: int,
    p1: int,
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    pending: wp.array(dtype=int),
): ...


@wp.kernel(enable_backward=False)
def integrate_scattered(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    f_acc: wp.array(dtype=wp.vec3),
    masses: wp.array(dtype=float),
    gravity: wp.vec3,
    dt: float,
    drag_factor: float,
    finish: int,
    cp: ContactParams,
    p0: int,
    p1: int,
    pending: wp.array(dtype=int),
    v_star: wp.array(dtype=wp.vec3),
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
):
    """CPU only, one thread: `particle_update` of particles [p0, p1) in order, for forces scattered into
    ``f_acc`` (read, then zeroed for the next substep's scatter), with the drag factor computed once (by
    `compute_drag_factor`: the same float) instead of per particle. The velocities go to ``v_star`` (see
    _VELOCITIES_CPU), then, with ``finish``, contacts and positions to ``x_out``/``v_out`` (``pending``, one
    int per particle, lists those near a contact: see _FINISH_FREE_CPU). (One looping
    thread: Warp's CPU code copies a kernel's arguments, the contact struct included, for every thread.)"""
    _velocities_cpu(v, f_acc, masses, gravity, dt, drag_factor, p0, p1, v_star)
    if finish != 0:
        # no collision stage: no candidates (`pending` stands in for the unread cand_count)
        _finish_free_cpu(x, v_star, dt, 0, pending, cp.mesh_ids.shape[0], cp.particle_world,
                         cp.world_mesh_start, cp.mesh_lo, cp.mesh_hi, cp.ground, p0, p1, x_out, v_out,
                         pending)
        for k in range(p0, p1):
            tid = pending[k]
            if tid < 0:
                break
            finish_particle(tid, x[tid], v_star[tid], masses[tid], dt, cp, x_out, v_out)


@wp.func
def pair_impulse(
    x: wp.array(dtype=wp.vec3),
    v_star: wp.array(dtype=wp.vec3),
    masses: wp.array(dtype=float),
    masks: wp.array(dtype=int),
    collision_dist: float,
    e: float,
    mu: float,
    tid: int,
    idx: int,
):
    """PhysTwin's impulse on particle ``tid`` from candidate ``idx``: (counted, normal part, tangential
    part); zero and not counted unless the pair is of different masks, closer than the collision
    distance and approaching."""
    x1 = x[tid]
    v1 = v_star[tid]
    dis = x[idx] - x1
    dis_len = wp.length(dis)
    rel_v = v_star[idx] - v1
    hit = float(0.0)  # noqa: UP018 (Warp needs a typed dynamic variable)
    j_n = wp.vec3(0.0, 0.0, 0.0)
    j_t = wp.vec3(0.0, 0.0, 0.0)
    if masks[idx] != masks[tid] and dis_len < collision_dist and wp.dot(dis, rel_v) < -1.0e-4:
        hit = 1.0
        n = dis / wp.max(dis_len, 1e-6)
        v_n = wp.dot(rel_v, n) * n
        v_t = rel_v - v_n
        inv_m = 1.0 / masses[tid] + 1.0 / masses[idx]
        j_n = -(1.0 + e) * v_n / inv_m
        a = wp.max(0.0, 1.0 - mu * (1.0 + e) * wp.length(v_n) / wp.max(wp.length(v_t), 1e-6))
        j_t = (a - 1.0) * v_t / inv_m
    return hit, j_n, j_t


@wp.func
def collide_particle(
    tid: int, x: wp.array(dtype=wp.vec3), v_star: wp.array(dtype=wp.vec3), masses: wp.array(dtype=float),
    masks: wp.array(dtype=int), collision_dist: float, e: float, mu: float, cand: wp.array2d(dtype=int),
    cand_count: wp.array(dtype=int), dt: float, cp: ContactParams, x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
):
    """`collide_and_finish` of one particle."""
    v1 = v_star[tid]
    m1 = masses[tid]
    valid = float(0.0)  # noqa: UP018 (Warp needs a typed dynamic variable)
    j_sum = wp.vec3(0.0, 0.0, 0.0)
    for k in range(cand_count[tid]):
        hit, j_n, j_t = pair_impulse(x, v_star, masses, masks, collision_dist, e, mu, tid, cand[tid, k])
        if hit > 0.0:
            valid = valid + 1.0
            j_sum = j_sum + j_n + j_t
    if valid > 0.0:
        v1 = v1 - (j_sum / valid) / m1
    finish_particle(tid, x[tid], v1, m1, dt, cp, x_out, v_out)


@wp.kernel(enable_backward=False)
def collide_and_finish(
    x: wp.array(dtype=wp.vec3),
    v_star: wp.array(dtype=wp.vec3),
    masses: wp.array(dtype=float),
    masks: wp.array(dtype=int),
    collision_dist: float,
    cand: wp.array2d(dtype=int),
    cand_count: wp.array(dtype=int),
    dt: float,
    cp: ContactParams,
    p0: int,
    p1: int,
    per_thread: int,
    pending: wp.array(dtype=int),
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
):
    """Particle-particle impulses averaged over the counted pairs (PhysTwin), then meshes, ground, x, for
    particles [p0, p1): thread i serves ``per_thread`` of them in order from p0 + i * per_thread (CUDA: 1;
    CPU: all, in one thread, see `integrate_scattered`, with ``pending`` one int per particle: particles
    without a candidate or other contact are moved natively, see _FINISH_FREE_CPU; CUDA: ``pending``
    empty).
    (Not differentiable: the loop carries its sums; the taped path uses `pair_impulses` + `apply_impulses`,
    which add in the same order.)"""
    i0 = p0 + wp.tid() * per_thread
    i1 = wp.min(i0 + per_thread, p1)
    e = wp.clamp(cp.coeffs[2], 0.0, 1.0)
    mu = wp.clamp(cp.coeffs[3], 0.0, 2.0)
    if pending.shape[0] > 0:
        _finish_free_cpu(x, v_star, dt, 1, cand_count, cp.mesh_ids.shape[0], cp.particle_world,
                         cp.world_mesh_start, cp.mesh_lo, cp.mesh_hi, cp.ground, i0, i1, x_out, v_out,
                         pending)
        for k in range(i0, i1):
            tid = pending[k]
            if tid < 0:
                break
            collide_particle(tid, x, v_star, masses, masks, collision_dist, e, mu, cand, cand_count, dt, cp,
                             x_out, v_out)
    else:
        for tid in range(i0, i1):
            collide_particle(tid, x, v_star, masses, masks, collision_dist, e, mu, cand, cand_count, dt, cp,
                             x_out, v_out)


@wp.kernel
def pair_impulses(
    x: wp.array(dtype=wp.vec3),
    v_star: wp.array(dtype=wp.vec3),
    masses: wp.array(dtype=float),
    masks: wp.array(dtype=int),
    collision_dist: float,
    cand: wp.array2d(dtype=int),
    cand_count: wp.array(dtype=int),
    cp: ContactParams,
    j_sum: wp.array(dtype=wp.vec3),
    valid: wp.array(dtype=float),
):
    """Differentiable form of collide_and_finish's candidate loop, one thread per (particle, candidate):
    on CPU the threads run candidate-fastest, so each particle's sum grows in the loop's order."""
    tid, k = wp.tid()
    if k < cand_count[tid]:
        e = wp.clamp(cp.coeffs[2], 0.0, 1.0)
        mu = wp.clamp(cp.coeffs[3], 0.0, 2.0)
        hit, j_n, j_t = pair_impulse(x, v_star, masses, masks, collision_dist, e, mu, tid, cand[tid, k])
        if hit > 0.0:
            wp.atomic_add(valid, tid, 1.0)
            wp.atomic_add(j_sum, tid, j_n)  # (j_sum + j_n) + j_t, as the loop adds them
            wp.atomic_add(j_sum, tid, j_t)


@wp.kernel
def apply_impulses(
    x: wp.array(dtype=wp.vec3),
    v_star: wp.array(dtype=wp.vec3),
    masses: wp.array(dtype=float),
    j_sum: wp.array(dtype=wp.vec3),
    valid: wp.array(dtype=float),
    dt: float,
    cp: ContactParams,
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
):
    """The averaged impulse of `pair_impulses`, then meshes, ground and the position update."""
    tid = wp.tid()
    v1 = v_star[tid]
    m1 = masses[tid]
    if valid[tid] > 0.0:
        v1 = v1 - (j_sum[tid] / valid[tid]) / m1
    finish_particle(tid, x[tid], v1, m1, dt, cp, x_out, v_out)


@wp.kernel(enable_backward=False)
def reduce_mesh_forces(cp: ContactParams, lists: wp.array2d(dtype=int), counts: wp.array(dtype=int),
                       meshes_per_world: int):
    """One thread: add the per-particle contact forces listed in ``lists[i, :counts[i]]`` (slots
    particle * meshes_per_world + mesh, see `mesh_contacts`), list after list, to their meshes and faces
    (each list in particle order, mesh order within a particle: the order of the direct atomic path on
    CPU when the lists are consecutive particle ranges); then zero the counts for the lists' next use."""
    for i in range(counts.shape[0]):
        for k in range(counts[i]):
            slot = lists[i, k]
            p = slot // meshes_per_world
            mesh = cp.world_mesh_start[cp.particle_world[p]] + slot - p * meshes_per_world
            wp.atomic_add(cp.mesh_force, mesh, cp.pm_force[slot])
            wp.atomic_add(cp.face_force, cp.face_offsets[mesh] + cp.pm_face[slot], cp.pm_force[slot])
        counts[i] = 0


@wp.func
def is_spring_neighbour(nbr_offsets: wp.array(dtype=int), nbr: wp.array(dtype=int), i: int, j: int):
    lo = nbr_offsets[i]
    hi = nbr_offsets[i + 1]
    while lo < hi:
        mid = (lo + hi) // 2
        val = nbr[mid]
        if val == j:
            return True
        if val < j:
            lo = mid + 1
        else:
            hi = mid
    return False


@wp.kernel(enable_backward=False)
def build_candidates(
    grid: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    masks: wp.array(dtype=int),
    particle_world: wp.array(dtype=int),
    nbr_offsets: wp.array(dtype=int),
    nbr: wp.array(dtype=int),
    cand_radius: float,
    query_radius: float,
    base: int,
    first: int,
    cand: wp.array2d(dtype=int),
    cand_count: wp.array(dtype=int),
):
    """Once per frame: other-mask particles strictly closer than ``cand_radius`` (max cand width),
    excluding spring neighbours. ``grid`` holds the particles ``x[base:]`` (grid index ``j`` is particle
    ``base + j``); thread ``i`` serves particle ``first + i``."""
    tid = first + wp.tid()
    p = x[tid]
    mask = masks[tid]
    max_c = cand.shape[1]
    q = wp.hash_grid_query(grid, p, query_radius, particle_world[tid])
    idx = int(0)  # noqa: UP018 (Warp needs a typed dynamic variable)
    c = int(0)  # noqa: UP018 (Warp needs a typed dynamic variable)
    while wp.hash_grid_query_next(q, idx):
        j = base + idx
        if j != tid and masks[j] != mask and c < max_c:
            if wp.length(x[j] - p) < cand_radius:
                if not is_spring_neighbour(nbr_offsets, nbr, tid, j):
                    cand[tid, c] = j
                    c += 1
    cand_count[tid] = c


@wp.kernel(enable_backward=False)
def interpolate_points(
    p_from: wp.array(dtype=wp.vec3), p_to: wp.array(dtype=wp.vec3), t: float, out: wp.array(dtype=wp.vec3)
):
    i = wp.tid()
    a = p_from[i]
    out[i] = a + (p_to[i] - a) * t


@wp.kernel(enable_backward=False)
def kinematic_bounds(
    p_from: wp.array(dtype=wp.vec3),
    p_to: wp.array(dtype=wp.vec3),
    first: wp.array(dtype=int),
    count: wp.array(dtype=int),
    mesh: wp.array(dtype=int),
    pad: float,
    lo: wp.array(dtype=wp.vec3),
    hi: wp.array(dtype=wp.vec3),
):
    """One thread per kinematic mesh: the box of its vertices at the frame's start and end (so at every
    substep, which interpolates them), grown by `pad`, into slot `mesh[k]`."""
    k = wp.tid()
    a = first[k]
    b = p_from[a]
    c = p_from[a]
    for i in range(a, a + count[k]):
        b = wp.min(b, wp.min(p_from[i], p_to[i]))
        c = wp.max(c, wp.max(p_from[i], p_to[i]))
    lo[mesh[k]] = b - wp.vec3(pad, pad, pad)
    hi[mesh[k]] = c + wp.vec3(pad, pad, pad)


@wp.kernel(enable_backward=False)
def vertex_velocities(
    p_from: wp.array(dtype=wp.vec3), p_to: wp.array(dtype=wp.vec3), inv_t: float, out: wp.array(dtype=wp.vec3)
):
    i = wp.tid()
    out[i] = (p_to[i] - p_from[i]) * inv_t
