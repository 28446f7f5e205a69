"""Semi-implicit Euler solver for :class:`SpringMassModel` (PhysTwin order of operations)."""

from __future__ import annotations

import warnings
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import warp as wp

from twinbench._runtime import cpu_cores
from twinbench.errors import SimulationDiverged

from . import kernels as K
from .frames import FrameBuffers, FrameExecutor, FrameExecutorFailed, Part, replayable, worlds_part
from .model import Control, SpringMassModel, State
from .split import SplitFrames, wants_split


def check_divergence(state: State, max_speed: float = 100.0) -> np.ndarray:
    """Indices of particles whose position/velocity is non-finite or whose speed exceeds ``max_speed``
    (m/s). Empty when the state is healthy. Never raises."""
    x = state.x.numpy()
    v = state.v.numpy()
    bad = ~np.all(np.isfinite(x), axis=1) | ~np.all(np.isfinite(v), axis=1)
    with np.errstate(invalid="ignore", over="ignore"):
        bad |= ~(np.linalg.norm(v.astype(np.float64), axis=1) <= max_speed)
    return np.flatnonzero(bad)


def default_threads(model: SpringMassModel) -> int:
    """Threads of a many-world model on CPU: one per core, at most one per world (1 on CUDA or for one
    world, which splits its frames over two processes instead when it is large enough: physics.split)."""
    if model.num_worlds == 1 or not str(model.device).startswith("cpu"):
        return 1
    return max(1, min(cpu_cores(), model.num_worlds))


class SpringMassSolver:
    """Advances a :class:`SpringMassModel`; one :meth:`step` is one substep, :meth:`simulate_frame`
    all ``params.substeps`` of one frame, run by the solver's frame executor (`executor`, chosen here:
    `RecordedFrames` on one core, `ThreadedWorlds` for many worlds on CPU threads, `split.SplitFrames` for one
    large world over two processes; see physics.frames).

    Per substep: spring + dashpot forces (summed per particle in spring order: scattered in one pass on
    CPU, gathered per particle on CUDA; PhysTwin's atomics on the differentiable path), gravity and drag,
    particle-particle impulses (candidates rebuilt once per frame), mesh contacts (relative to the mesh
    velocity), ground with time of impact. On CPU the per-particle stages run as one thread looping over
    its particles (the same per-particle functions as CUDA's thread per particle).
    """

    def __init__(self, model: SpringMassModel, *, use_graph: bool = True, max_speed: float = 100.0,
                 threads: int | None = None):
        self.model = model
        self.max_speed = float(max_speed)
        p = model.params
        dev = model.device
        self.device = dev
        n = model.num_particles
        self._spring_f = wp.zeros(model.num_springs, dtype=wp.vec3, device=dev)
        self._no_list = wp.zeros(0, dtype=int, device=dev)
        self._f = wp.zeros(n, dtype=wp.vec3, device=dev)
        self._drag_factors: dict[tuple[float, float], float] = {}  # see _drag_factor (CPU)
        self._gravity = wp.vec3(*[float(g) for g in p.gravity])
        self._collide = model.particle_collisions  # fixed topology: decided once, not per substep
        # CPU: spring forces scattered to their ends in one sequential pass per thread or process (same sums,
        # same order as the per-particle gather that the parallel CUDA launch uses)
        self._scatter = str(dev).startswith("cpu")
        # CPU: per particle, the particles near a contact in this process's range (see K.integrate_scattered)
        self._pending = wp.zeros(n if self._scatter else 0, dtype=int, device=dev)
        if self._scatter:  # the drag factor of the model's parameters, outside any capture
            self._drag_factor(float(p.dt), float(p.drag_damping))
        nm = len(model.meshes)
        nfaces = sum(m.faces.shape[0] for m in model.meshes)
        self._mesh_force = wp.zeros(max(nm, 1), dtype=wp.vec3, device=dev)
        self._face_force = wp.zeros(max(nfaces, 1), dtype=wp.vec3, device=dev)
        self._last_mesh_force = np.zeros((nm, 3))
        self._last_face_force = np.zeros((nfaces, 3))
        cp = K.ContactParams()
        cp.mesh_ids = wp.array([m.mesh.id for m in model.meshes], dtype=wp.uint64, device=dev)
        cp.mesh_elas = wp.array([m.restitution for m in model.meshes], dtype=float, device=dev)
        cp.mesh_fric = wp.array([m.friction for m in model.meshes], dtype=float, device=dev)
        cp.face_offsets = wp.array([m.face_offset for m in model.meshes], dtype=int, device=dev)
        cp.margin = float(p.mesh_margin)
        cp.mesh_force = self._mesh_force
        cp.face_force = self._face_force
        cp.particle_world = model.particle_world
        cp.world_mesh_start = model.world_mesh_start
        cp.per_particle = 0
        cp.pm_force = wp.zeros(0, dtype=wp.vec3, device=dev)
        cp.pm_face = wp.zeros(0, dtype=int, device=dev)
        cp.pm_list = wp.zeros(0, dtype=int, device=dev)
        cp.pm_count = wp.zeros(0, dtype=int, device=dev)
        cp.ground = int(p.ground)
        cp.coeffs = model.contact_coeffs  # read each launch: changing them needs no recapture
        # per mesh, a box a particle must be inside to be queried (exactly outside: farther than the margin
        # from every point of the mesh); kinematic meshes' boxes follow each frame's motion
        self._pad = 1.01 * float(p.mesh_margin) + 1e-5
        lo = np.array([m.vertices.min(0) - self._pad for m in model.meshes], np.float32).reshape(-1, 3)
        hi = np.array([m.vertices.max(0) + self._pad for m in model.meshes], np.float32).reshape(-1, 3)
        cp.mesh_lo = wp.array(lo, dtype=wp.vec3, device=dev)
        cp.mesh_hi = wp.array(hi, dtype=wp.vec3, device=dev)
        kin = [i for i, m in enumerate(model.meshes) if m.kinematic]
        self._kin_first = wp.array([model.meshes[i].vertex_offset for i in kin], dtype=int, device=dev)
        self._kin_count = wp.array([model.meshes[i].vertices.shape[0] for i in kin], dtype=int, device=dev)
        self._kin_mesh = wp.array(kin, dtype=int, device=dev)
        self._cp = cp
        self._kinematic = kin
        self._cand_width = p.max_collision_candidates if self._collide else 1
        self._buffers = FrameBuffers.allocate(model, self._cand_width, cp)
        self._own_buffers = True  # whether _buffers are the solver's own (else an executor placed them)
        self._frame_t = np.float32(p.dt) * np.float32(p.substeps)
        # Many worlds on CPU: contiguous groups of worlds, each group's frame on its own thread (worlds never
        # interact, so each array element is written by one thread exactly as with one thread).
        self.threads = default_threads(model) if threads is None else int(threads)
        if self.threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        self._all = worlds_part(model, 0, model.num_worlds)
        cuts = np.linspace(0, model.num_worlds, min(self.threads, model.num_worlds) + 1).round().astype(int)
        groups = [worlds_part(model, int(a), int(b)) for a, b in zip(cuts[:-1], cuts[1:], strict=True)]
        # one hash grid per group of worlds (w0, w1), points grouped by world: a query sees its own world's
        parts = [self._all, *groups] if self._collide else []
        self._grids = {(wr.w0, wr.w1): wp.HashGrid(64, 64, 64, device=dev) for wr in parts}
        self._use_graph = use_graph
        self._executor: FrameExecutor
        if len(groups) > 1:
            self._executor = ThreadedWorlds(self, groups)
        elif wants_split(model, self.threads if threads is not None else cpu_cores()):
            # one world on several cores: half of every substep in a helper process (see physics.split)
            self._executor = SplitFrames(self)
        else:
            self._executor = RecordedFrames(self, use_graph)

    # ------------------------------------------------------------------ one substep
    def _t(self, substep_index: int) -> float:
        s = self.model.params.substeps
        return float(np.float32(substep_index + 1) / np.float32(s))

    def _go(self, kernel, dim: int, inputs: list, outputs: list, ops: list | None) -> None:
        """Launch now, or record the launch into ``ops`` (see `replayable`)."""
        if ops is None:
            wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=self.device)
        else:
            launch = wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=self.device,
                               record_cmd=True)
            ops.append(replayable(launch))

    def _update_kinematic_meshes(self, control: Control, substep_index: int, ops: list | None = None,
                                 wr: Part | None = None) -> None:
        """The worlds' kinematic mesh vertices at this substep (one launch), then each mesh's BVH refit."""
        m = self.model
        wr = wr or self._all
        a, b = wr.kin_vertices
        t = self._t(substep_index)
        self._go(K.interpolate_points, b - a, [control.kin_from[a:b], control.kin_to[a:b], t],
                 [m.kin_points[a:b]], ops)
        for mid in wr.kinematic:
            mesh = m.meshes[mid].mesh
            if ops is None:
                mesh.refit()
            else:
                ops.append(mesh.refit)

    # ------------------------------------------------------------------ for frame executors
    @property
    def executor(self) -> FrameExecutor:
        """What runs this solver's frames (see physics.frames): its ``name`` is "one-core", "threads" or
        "split"."""
        return self._executor

    @property
    def buffers(self) -> FrameBuffers:
        """The arrays the frames write (the solver's own, or those an executor placed: `use_buffers`)."""
        return self._buffers

    def use_buffers(self, buffers: FrameBuffers | None) -> None:
        """Write frames into ``buffers`` (placed by an executor before it records a frame, e.g. in memory
        shared with another process; the solver's own are released); None: buffers of its own again."""
        if buffers is not None:
            self._buffers, self._own_buffers = buffers, False
        elif not self._own_buffers:
            self._buffers = FrameBuffers.allocate(self.model, self._cand_width, self._cp)
            self._own_buffers = True

    @property
    def has_kinematic_meshes(self) -> bool:
        return bool(self._kinematic)

    def begin_frame(self, state: State, control: Control) -> State:
        """A frame's start: `state` copied into the frame's first buffer (returned) and the kinematic
        meshes' velocities for the frame's motion."""
        a = self.buffers.states[0]
        a.assign(state)
        if self.has_kinematic_meshes:
            self.set_mesh_velocities(control)
        return a

    def set_mesh_velocities(self, control: Control) -> None:
        """The kinematic meshes' vertex velocities and boxes for this frame's motion."""
        m = self.model
        wp.launch(K.vertex_velocities, dim=m.kin_points.shape[0],
                  inputs=[control.kin_from, control.kin_to, float(1.0 / self._frame_t)],
                  outputs=[m.kin_velocities], device=self.device)
        wp.launch(K.kinematic_bounds, dim=self._kin_mesh.shape[0],
                  inputs=[control.kin_from, control.kin_to, self._kin_first, self._kin_count, self._kin_mesh,
                          self._pad], outputs=[self._cp.mesh_lo, self._cp.mesh_hi], device=self.device)

    def rebuild_collision_candidates(self, state: State, wr: Part | None = None,
                                     rows: tuple[int, int] | None = None) -> None:
        """Rebuild the particle-particle candidate lists from ``state.x`` (done once per frame): the lists of
        the particles ``rows`` (default: all of the worlds ``wr``)."""
        m = self.model
        if not self._collide:
            return
        wr = wr or self._all
        cd = float(m.params.collision_dist)
        cand_r = cd * float(m.params.candidate_radius_scale)
        cell = max(cd * 5.0, cand_r)  # PhysTwin: hash cell (and query radius) 5 * collision_dist
        # Only particles closer than cand_r become candidates, so the lookup covers the cells within cand_r
        # (with a margin over float rounding): a query visits the cells of its box in lexicographic order,
        # so the candidates and their order are those of PhysTwin's 5 * collision_dist lookup, at a
        # fraction of the visits.
        lookup_r = min(cell, 1.25 * cand_r)
        p0, p1 = wr.particles
        r0, r1 = rows or (p0, p1)
        grid = self._grids[(wr.w0, wr.w1)]
        grid.build(state.x[p0:p1], cell, groups=m.particle_world[p0:p1])
        wp.launch(K.build_candidates, dim=r1 - r0,
                  inputs=[grid.id, state.x, m.masks, m.particle_world, m.nbr_offsets, m.nbr, cand_r, lookup_r,
                          p0, r0],
                  outputs=[self._buffers.cand, self._buffers.cand_count], device=self.device)

    def update_stiffness(self, ops: list | None = None, wr: Part | None = None) -> None:
        m = self.model
        for a, b in (wr or self._all).springs:
            limits = [float(m.params.spring_Y_min), float(m.params.spring_Y_max)]
            inputs = [m.log_y[a:b], m.rest_lengths[a:b], *limits]
            self._go(K.effective_stiffness, b - a, inputs, [self._buffers.ry[a:b]], ops)

    def _drag_factor(self, dt: float, drag: float) -> float:
        """exp(-dt * drag) as the kernels compute it (one Warp launch per new pair, then cached)."""
        key = (dt, drag)
        if key not in self._drag_factors:
            if wp.get_device(self.device).is_capturing:  # a captured launch would not run here
                raise RuntimeError(f"SpringMassSolver: a first step with dt={dt}, drag_damping={drag} must "
                                   "run outside a graph capture (it computes the drag factor once)")
            out = wp.zeros(1, dtype=float, device=self.device)
            wp.launch(K.compute_drag_factor, dim=1, inputs=[dt, drag], outputs=[out], device=self.device)
            self._drag_factors[key] = float(out.numpy()[0])
        return self._drag_factors[key]

    def _zero_forces(self, ops: list | None = None, wr: Part | None = None) -> None:
        """Scatter path: the part's particle forces to zero (each substep's integration zeroes them again
        after reading; this covers a first frame and one cut short). A split frame's part zeroes every
        particle: its process owns `f` and adds the springs across the cut to both ends, the other part's
        sums only to be dropped."""
        if self._scatter:
            wr = wr or self._all
            p0, p1 = (0, self.model.num_particles) if wr.touching is not None else wr.particles
            self._go(K.zero_forces, p1 - p0, [p0], [self._f], ops)

    def _launch_substep(self, state_in: State, state_out: State, control: Control, dt: float,
                        substep_index: int, grad: bool, ops: list | None = None,
                        wr: Part | None = None, sync=None) -> None:
        """One substep's launches over the part `wr` of the model. `sync` (recorded mode): a barrier with the
        process that runs the other part, recorded wherever one stage reads what the other part wrote."""
        m = self.model
        p = m.params
        n = m.num_particles
        wr = wr or self._all
        p0, p1 = wr.particles
        t = self._t(substep_index)
        tail = [float(p.dashpot_damping), control.ctrl_from, control.ctrl_to, t, n]
        buf = self._buffers
        cp = buf.contacts[substep_index % 2]
        spring_f = self._spring_f  # per-spring forces (gather path); unused by the atomic path
        if grad:
            if wr is not self._all:
                raise ValueError("the differentiable path runs every world in one launch")
            f = wp.zeros(n, dtype=wp.vec3, device=self.device, requires_grad=True)
            wp.launch(K.accumulate_spring_forces, dim=m.num_springs,
                      inputs=[state_in.x, state_in.v, m.springs, m.rest_lengths, m.log_y,
                              float(p.spring_Y_min), float(p.spring_Y_max), *tail],
                      outputs=[f], device=self.device)
            v_star = wp.zeros(n, dtype=wp.vec3, device=self.device, requires_grad=True)
        elif self._scatter:
            # CPU: each spring added to its ends in spring order (f is zero: see _zero_forces)
            if not (state_in.x.is_contiguous and state_in.v.is_contiguous):
                raise ValueError("step(): state_in.x and state_in.v must be contiguous Warp arrays "
                                 "(make states with model.state())")
            f = self._f
            v_star = buf.v_star
            head = [state_in.x, state_in.v, m.springs, buf.ry, float(p.dashpot_damping)]
            cut = m.num_object_springs  # object springs [0, cut), then control springs
            if wr.touching is not None:  # a split frame's part: the springs touching it
                runs = [(c, first, count, self._no_list if ids is None else ids)
                        for c, first, count, ids in wr.touching]
            else:
                runs = [(lo >= cut, lo, hi - lo, self._no_list) for a, b in wr.springs
                        for lo, hi in ((a, min(b, cut)), (max(a, cut), b))]
            for to_control, first, count, ids in runs:
                if count <= 0:
                    continue
                if to_control:
                    args = [*head, control.ctrl_from, control.ctrl_to, t, n, p0, p1, first, ids]
                    self._go(K.scatter_control_springs, count, args, [f], ops)
                else:
                    self._go(K.scatter_object_springs, 1, [*head, first, count, ids], [f], ops)
        else:
            f = self._f
            v_star = buf.v_star
            for a, b in wr.springs:
                inputs = [state_in.x, state_in.v, m.springs[a:b], buf.ry[a:b], *tail]
                self._go(K.eval_spring_forces, b - a, inputs, [spring_f[a:b]], ops)
        collide = self._collide
        if self._scatter and not grad:
            self._go(K.integrate_scattered, 1,
                     [state_in.x, state_in.v, f, m.masses, self._gravity, float(dt),
                      self._drag_factor(float(dt), float(p.drag_damping)), int(not collide), cp, p0, p1,
                      self._pending],
                     [v_star, state_out.x, state_out.v], ops)
        else:
            self._go(K.particle_update, p1 - p0,
                     [state_in.x, state_in.v, spring_f, m.inc_offsets, m.inc_springs, f, int(not grad),
                      m.masses, self._gravity, float(dt), float(p.drag_damping), int(not collide), cp, p0],
                     [v_star, state_out.x, state_out.v], ops)
        if collide and grad:  # the differentiable form (same sums in the same order)
            j_sum = wp.zeros(n, dtype=wp.vec3, device=self.device, requires_grad=True)
            valid = wp.zeros(n, dtype=float, device=self.device, requires_grad=True)
            wp.launch(K.pair_impulses, dim=(n, buf.cand.shape[1]),
                      inputs=[state_in.x, v_star, m.masses, m.masks, float(p.collision_dist), buf.cand,
                              buf.cand_count, self._cp], outputs=[j_sum, valid], device=self.device)
            wp.launch(K.apply_impulses, dim=n,
                      inputs=[state_in.x, v_star, m.masses, j_sum, valid, float(dt), self._cp],
                      outputs=[state_out.x, state_out.v], device=self.device)
        elif collide:
            if sync is not None:
                ops.append(sync)  # impulses read the other part's v_star
            args = [state_in.x, v_star, m.masses, m.masks, float(p.collision_dist), buf.cand,
                    buf.cand_count, float(dt), cp]
            threads, per = (1, p1 - p0) if self._scatter else (p1 - p0, 1)  # CPU: one thread for the part
            self._go(K.collide_and_finish, threads, [*args, p0, p1, per, self._pending],
                     [state_out.x, state_out.v], ops)
        if sync is not None:
            ops.append(sync)  # the next substep reads every particle

    def step(self, state_in: State, state_out: State, control: Control, dt: float | None = None,
             substep_index: int = 0) -> None:
        """Advance one substep from ``state_in`` into ``state_out`` (distinct states).

        ``substep_index`` places the control points and kinematic meshes at ``(s+1)/substeps`` of the
        frame's motion. Collision candidates are not rebuilt here (see
        :meth:`rebuild_collision_candidates`). Recorded by an active ``wp.Tape`` when the model was
        finalized with ``requires_grad=True``.
        """
        if state_in is state_out:
            raise ValueError("state_in and state_out must be different State objects")
        dt = self.model.params.dt if dt is None else float(dt)
        if self._kinematic:
            if substep_index == 0:
                self.set_mesh_velocities(control)
            self._update_kinematic_meshes(control, substep_index)
        if not self.model.requires_grad:
            self.update_stiffness()
            self._zero_forces()
        self._launch_substep(state_in, state_out, control, dt, substep_index, grad=self.model.requires_grad)

    # ------------------------------------------------------------------ one frame
    def record_frame(self, control: Control, ops: list | None = None, wr: Part | None = None,
                     sync=None, after_substep=None) -> State:
        """One frame's launches over the part ``wr`` (default: every world) from ``buffers.states[0]``: run
        now, or recorded into ``ops`` (see `replayable`). Returns the buffer state that holds the frame's end.
        ``sync``: a split frame's barrier with the other side (see `_launch_substep`; the stiffness is then
        updated before the frame, not recorded); ``after_substep``: (even, odd) substeps' closing ops."""
        a, b = self._buffers.states
        p = self.model.params
        if sync is None:  # (a split frame updates the stiffness before it starts)
            self.update_stiffness(ops, wr)  # once per frame; a replay reads the current log Y
        self._zero_forces(ops, wr)
        for s in range(p.substeps):
            src, dst = (a, b) if s % 2 == 0 else (b, a)
            if self._kinematic:
                self._update_kinematic_meshes(control, s, ops, wr)
            self._launch_substep(src, dst, control, p.dt, s, grad=False, ops=ops, wr=wr, sync=sync)
            if after_substep is not None:  # ops for even and odd substeps
                ops.append(after_substep[s % 2])
        return b if p.substeps % 2 == 1 else a

    def simulate_frame_tape(self, state: State, control: Control) -> list[State]:
        """Differentiable frame: every substep writes a new State (nothing overwritten), so an active
        ``wp.Tape`` can run backward to ``model.log_y`` and the initial state. Needs a model finalized
        with ``requires_grad=True``. Returns the substep states ``[state, s1, ..., s_substeps]``.

        Known limit: moving meshes are refitted in place, so their contacts replay at the last pose in
        the backward pass (gradients through kinematic-mesh contacts are approximate).
        """
        if not self.model.requires_grad:
            raise ValueError("simulate_frame_tape needs ModelBuilder.finalize(requires_grad=True)")
        self.rebuild_collision_candidates(state)
        states = [state]
        for s in range(self.model.params.substeps):
            states.append(self.model.state())
            self.step(states[-2], states[-1], control, substep_index=s)
        return states

    def simulate_frame(self, state: State, control: Control, *, check: bool = True) -> State:
        """Run all substeps of one frame in place on ``state`` and return it (fast path, not taped).

        Rebuilds the collision candidates from the frame-start positions, runs the frame with the solver's
        executor (`executor`: on one core a captured graph when possible, i.e. no kinematic meshes, else
        recorded launches; groups of worlds on threads; or one world split over two processes, see
        physics.frames), records the mean contact force per mesh, and raises
        :class:`SimulationDiverged` when ``check`` and a particle became non-finite or too fast.
        """
        if self._scatter:  # before any capture below
            self._drag_factor(float(self.model.params.dt), float(self.model.params.drag_damping))
        try:
            retire = self._run_frame(state, control)
        except FrameExecutorFailed as err:
            self._fall_back(err)
            self._run_frame(state, control)
        else:
            if retire is not None:
                self._fall_back(retire)
        return self._frame_end(state, check)

    def _run_frame(self, state: State, control: Control) -> str | None:
        self._mesh_force.zero_()
        self._face_force.zero_()
        return self._executor.run_frame(state, control)

    def _fall_back(self, err: BaseException | str) -> None:
        warnings.warn(f"physics: running one world on one core from now on ({err})", stacklevel=3)
        self.close()

    def close(self) -> None:
        """Stop the executor's helper process or threads, if any (also done at exit); later frames run on one
        core, with the same results."""
        if self._executor.name != "one-core":
            self._executor.close()
            self._executor = RecordedFrames(self, self._use_graph)

    def _frame_end(self, state: State, check: bool) -> State:
        nm = len(self.model.meshes)
        if nm:  # no meshes: the force buffers stay empty, no device->host copies
            scale = 1.0 / self.model.params.substeps
            self._last_mesh_force = self._mesh_force.numpy()[:nm].astype(np.float64) * scale
            nf = self._last_face_force.shape[0]
            self._last_face_force = self._face_force.numpy()[:nf].astype(np.float64) * scale
        if check:
            bad = check_divergence(state, self.max_speed)
            if bad.size:
                raise SimulationDiverged(bad)
        return state

    def mesh_contact_force(self, mesh_id: int, per_face: bool = False) -> np.ndarray:
        """Mean force (N) the mesh exerted on the particles over the last frame: (3,) or per face (F, 3)."""
        if not 0 <= mesh_id < len(self.model.meshes):
            raise ValueError(f"mesh_id={mesh_id} is not a mesh of this model "
                             f"({len(self.model.meshes)} meshes)")
        if not per_face:
            return self._last_mesh_force[mesh_id].copy()
        info = self.model.meshes[mesh_id]
        return self._last_face_force[info.face_offset: info.face_offset + info.faces.shape[0]].copy()


class RecordedFrames:
    """Frames on one core (or one CUDA device): the frame's launches captured as a graph when no mesh moves,
    else recorded launches replayed (BVH refits are host calls that a graph cannot hold); plain launches
    without ``use_graph``. A recording is reused while the same Control object comes back."""

    name = "one-core"

    def __init__(self, solver: SpringMassSolver, use_graph: bool = True):
        self.solver, self.use_graph = solver, use_graph
        self._plan = self._key = self._out = None

    def run_frame(self, state: State, control: Control) -> None:
        s = self.solver
        a = s.begin_frame(state, control)
        s.rebuild_collision_candidates(a)
        key = control  # compared by identity; holding it keeps its arrays (baked into the plan) alive
        if not self.use_graph:
            out = s.record_frame(control)
        elif not s.has_kinematic_meshes:
            if self._plan is None or self._key is not key:
                with wp.ScopedCapture(device=s.device, force_module_load=True) as cap:
                    out = s.record_frame(control)
                self._plan, self._key, self._out = cap.graph, key, out
            wp.capture_launch(self._plan)
            out = self._out
        else:
            if self._plan is None or self._key is not key:
                ops: list = []
                out = s.record_frame(control, ops)
                self._plan, self._key, self._out = ops, key, out
            for op in self._plan:
                op()
            out = self._out
        state.assign(out)

    def close(self) -> None:
        self._plan = self._key = self._out = None


class ThreadedWorlds:
    """Frames of a many-world model on CPU: contiguous groups of worlds, each group's recorded launches
    replayed on its own thread (worlds never interact, so each array element is written by one thread
    exactly as with one thread; Warp's CPU kernels release the GIL)."""

    name = "threads"

    def __init__(self, solver: SpringMassSolver, groups: list[Part]):
        self.solver, self.groups = solver, groups
        self._pool = ThreadPoolExecutor(len(groups) - 1)
        self._plans = self._key = self._out = None

    def run_frame(self, state: State, control: Control) -> None:
        s = self.solver
        a = s.begin_frame(state, control)
        if self._plans is None or self._key is not control:
            plans = []
            for wr in self.groups:
                ops: list = []
                out = s.record_frame(control, ops, wr)
                plans.append(ops)
            self._plans, self._key, self._out = plans, control, out

        def run(group: int) -> None:
            s.rebuild_collision_candidates(a, self.groups[group])
            for op in self._plans[group]:
                op()

        futures = [self._pool.submit(run, g) for g in range(1, len(self.groups))]
        run(0)
        for fut in futures:
            fut.result()
        state.assign(self._out)

    def close(self) -> None:
        self._pool.shutdown()
        self._plans = self._key = self._out = None
