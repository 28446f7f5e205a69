"""One world on two CPU cores: a helper process runs the second half of every per-substep kernel.

Warp runs a CPU kernel on one core, and handing work between Python threads costs more (tens of us per
hand-off, the GIL) than half of a substep's kernel saves. So a frame is split between this process and a
spawned helper process instead: the arrays the substeps write (particle buffers, collision candidates,
per-particle contact forces) and the frame's controls live in one shared file mapping; each process
replays its own recorded launches (particles [0, n/2) here, the rest there; each sums the forces of the
springs touching its particles in spring order, so a spring across the cut is evaluated by both) and the
two meet at spin barriers on shared counters (a few us) wherever a stage reads what the other half wrote.
Each array element is written by exactly one process with the same arithmetic, and the mesh contact forces
are listed by each process in particle order and added list after list by `reduce_mesh_forces`, so a split
frame is bit-identical to a frame on one core. Between frames the helper blocks on a pipe (no spinning). If
the helper dies, or stalls (stopped, e.g. SIGSTOP: a wait at a barrier longer than max(STALL_TIMEOUT_S,
STALL_FRAMES median frames)), it is killed, the frame is run on one core and the solver stays there.

Spin barriers rely on x86's ordered stores (TSO): the split is only used on x86-64.
"""

from __future__ import annotations

import os
import pickle
import platform
import signal
import subprocess
import sys
import tempfile
import time
import weakref
from dataclasses import fields

import numpy as np
import warp as wp

from twinbench._runtime import quiet_warp, watch_parent

from . import kernels as K
from .frames import FrameBuffers, FrameExecutorFailed, Part, replayable
from .model import Control, SpringMassModel, State, device_meshes

SPLIT_MIN_WORK = 6000  # springs + 2 * particles below which one core is as fast as a split frame
CONTENDED_FRAMES = 3  # frames in a row with over 10 % of barriers waiting for a descheduled process
STALL_TIMEOUT_S, STALL_FRAMES = 10.0, 50  # a wait longer than max(these s, these median frames): stalled
_ALIGN = 64
_WP_FIELDS = {  # SpringMassModel array fields the helper rebuilds, with their Warp dtypes
    "springs": wp.vec2i, "rest_lengths": float, "log_y": float, "masses": float, "masks": int,
    "inc_offsets": int, "inc_springs": int, "nbr_offsets": int, "nbr": int, "particle_world": int,
    "world_mesh_start": int, "contact_coeffs": float,
}


class SplitFailed(FrameExecutorFailed):
    """The helper process of a split frame died or failed."""


def split_supported() -> bool:
    return platform.machine().lower() in ("x86_64", "amd64")


def wants_split(model: SpringMassModel, threads: int) -> bool:
    """Whether one world's frames should be split over two processes."""
    return (
        threads >= 2 and model.num_worlds == 1 and str(model.device).startswith("cpu")
        and not model.requires_grad and split_supported()
        and model.num_springs + 2 * model.num_particles >= SPLIT_MIN_WORK
    )


class SharedArrays:
    """Named numpy arrays in one file-backed mapping (`create` here, the constructor in the other process)."""

    def __init__(self, layout: dict, path: str, create: bool):
        self.layout, self.path = layout, path
        size = max(off + int(np.prod(shape)) * np.dtype(dt).itemsize for off, shape, dt in layout.values())
        self.mm = np.memmap(path, dtype=np.uint8, mode="w+" if create else "r+", shape=(max(size, 1),))
        self.np = {k: np.ndarray(shape, np.dtype(dt), buffer=self.mm, offset=off)
                   for k, (off, shape, dt) in layout.items()}

    @classmethod
    def create(cls, specs: dict) -> SharedArrays:
        layout, off = {}, 0
        for name, (shape, dt) in specs.items():
            layout[name] = (off, tuple(shape), np.dtype(dt).str)
            off += -(-max(int(np.prod(shape)) * np.dtype(dt).itemsize, 1) // _ALIGN) * _ALIGN
        folder = "/dev/shm" if os.path.isdir("/dev/shm") else tempfile.gettempdir()
        fd, path = tempfile.mkstemp(prefix="twinbench-split-", dir=folder)
        os.close(fd)
        return cls(layout, path, create=True)

    def wp(self, name: str, dtype) -> wp.array:
        return wp.array(self.np[name], dtype=dtype, device="cpu", copy=False)


def _specs(model: SpringMassModel, cand_width: int) -> dict:
    n, s = model.num_particles, model.num_springs
    kv = int(model.kin_points.shape[0])
    pm = n * len(model.meshes)
    f32, i32 = np.float32, np.int32
    return {
        "xa": ((n, 3), f32), "va": ((n, 3), f32), "xb": ((n, 3), f32), "vb": ((n, 3), f32),
        "ry": ((s, 2), f32), "v_star": ((n, 3), f32),
        "cand": ((n, cand_width), i32), "cand_count": ((n,), i32),
        "ctrl_from": ((model.num_control_points, 3), f32), "ctrl_to": ((model.num_control_points, 3), f32),
        "kin_from": ((kv, 3), f32), "kin_to": ((kv, 3), f32),
        # per substep parity (see _shared_buffers); the lists and counts also per side (0: main, 1: helper)
        "pm_force": ((2, pm, 3), f32), "pm_face": ((2, pm), i32),
        "pm_list": ((2, 2, pm), i32), "pm_count": ((2, 2), i32),
        "sync": ((8,), np.int64),  # 0: main phase, 1: helper phase, 2: helper ready, 3: helper failed
    }


def _shared_buffers(solver, shared: SharedArrays, side: int) -> tuple[FrameBuffers, Control]:
    """The solver's frame buffers in the shared arrays (this process is `side`), and the shared Control."""
    v3 = wp.vec3
    # Per-particle contact forces: each side lists its contacts in particle order, and the main side adds the
    # two lists to the meshes after each substep's last barrier. The helper may already be writing the next
    # substep's contacts then, so even and odd substeps write their own copy.
    cp = solver.buffers.contacts[0]
    buffers = FrameBuffers(
        states=tuple(State(shared.wp(f"x{k}", v3), shared.wp(f"v{k}", v3)) for k in "ab"),
        ry=shared.wp("ry", wp.vec2), v_star=shared.wp("v_star", v3), cand=shared.wp("cand", int),
        cand_count=shared.wp("cand_count", int),
        contacts=tuple(_per_particle_contacts(cp, shared, k, side) for k in (0, 1)),
    )
    ctl = Control(ctrl_from=shared.wp("ctrl_from", v3), ctrl_to=shared.wp("ctrl_to", v3),
                  kin_from=shared.wp("kin_from", v3), kin_to=shared.wp("kin_to", v3))
    for mid, info in enumerate(solver.model.meshes):
        if info.kinematic:
            span = slice(info.vertex_offset, info.vertex_offset + info.vertices.shape[0])
            ctl.mesh_from[mid], ctl.mesh_to[mid] = ctl.kin_from[span], ctl.kin_to[span]
    return buffers, ctl


def _per_particle_contacts(cp: K.ContactParams, shared: SharedArrays, parity: int, side: int):
    out = K.ContactParams()
    out.assign(cp)
    out.per_particle = 1
    a = shared.np
    arrays = {"pm_force": (a["pm_force"][parity], wp.vec3), "pm_face": (a["pm_face"][parity], int),
              "pm_list": (a["pm_list"][parity, side], int),
              "pm_count": (a["pm_count"][parity, side:side + 1], int)}
    for name, (view, dtype) in arrays.items():
        setattr(out, name, wp.array(view, dtype=dtype, device="cpu", copy=False))
    return out


def _payload(model: SpringMassModel) -> dict:
    out = {}
    for f in fields(model):
        value = getattr(model, f.name)
        if f.name in _WP_FIELDS:
            out[f.name] = value.numpy()
        elif f.name == "meshes":
            out[f.name] = [(m.vertices, m.faces, m.restitution, m.friction, m.kinematic) for m in value]
        elif f.name not in ("kin_points", "kin_velocities"):
            out[f.name] = value
    return out


def _model_from_payload(payload: dict) -> SpringMassModel:
    kw = dict(payload)
    for name, dtype in _WP_FIELDS.items():
        kw[name] = wp.array(payload[name], dtype=dtype, device="cpu")
    kw["meshes"], kw["kin_points"], kw["kin_velocities"] = device_meshes(payload["meshes"], "cpu")
    return SpringMassModel(**kw)


def _spring_runs(ids: np.ndarray, control: bool, device, min_run: int = 256) -> list[tuple]:
    """Launches for the ascending spring ids `ids`, in their order: runs of at least `min_run` consecutive ids
    as (control, first, count, None) ranges (no index list to read), the ids between them as (control, 0,
    count, ids) lists."""
    out, pending = [], []
    cuts = np.flatnonzero(np.diff(ids) != 1) + 1
    for run in np.split(ids, cuts) if ids.size else []:
        if run.size < min_run:
            pending.append(run)
            continue
        if pending:
            listed = np.concatenate(pending)
            out.append((control, 0, listed.size, wp.array(listed, dtype=int, device=device)))
            pending = []
        out.append((control, int(run[0]), run.size, None))
    if pending:
        listed = np.concatenate(pending)
        out.append((control, 0, listed.size, wp.array(listed, dtype=int, device=device)))
    return out


def _half(model: SpringMassModel, second: bool) -> Part:
    """The part of one half of a one-world model (see physics.frames.Part)."""
    n = model.num_particles
    kin = tuple(i for i, m in enumerate(model.meshes) if m.kinematic)
    kv = (0, int(model.kin_points.shape[0]))
    p0, p1 = (n // 2, n) if second else (0, n // 2)
    ends = model.springs_np
    touching = np.flatnonzero(((ends >= p0) & (ends < p1)).any(axis=1)).astype(np.int32)
    cut = model.num_object_springs
    runs = (_spring_runs(touching[touching < cut], False, model.device)
            + _spring_runs(touching[touching >= cut], True, model.device))
    return Part(0, 0, (p0, p1), (), kv, kin, tuple(runs))  # springs: the runs (the main side sets stiffness)


class _Barrier:
    """Spin barrier of two processes on shared counters: `mine` counts this side's arrivals."""

    def __init__(self, sync: np.ndarray, mine: int, other: int, alive, stalled=None):
        self.sync, self.mine, self.other, self.alive = sync, mine, other, alive
        self.stalled = stalled  # called with the seconds waited once a wait exceeds timeout_s
        self.timeout_s = STALL_TIMEOUT_S
        self.phase = int(sync[mine])
        self.slow = 0  # waits long enough to yield the core (the other side was not running)

    def __call__(self) -> None:
        self.phase += 1
        sync, other, phase = self.sync, self.other, self.phase
        sync[self.mine] = phase
        spins, t0 = 0, 0.0
        while sync[other] < phase:
            spins += 1
            if spins > 2000:  # the other side is not running (more busy processes than cores): let it
                if spins == 2001:
                    self.slow += 1
                time.sleep(0)
            if spins & 0x3FFF == 0:
                self.alive()
                now = time.monotonic()
                t0 = t0 or now
                if self.stalled is not None and now - t0 > self.timeout_s:
                    self.stalled(now - t0)


class SplitFrames:
    """The main side of split frames for `solver` (see the module docstring): a frame executor (see
    physics.frames) whose helper process starts with the first frame."""

    name = "split"

    def __init__(self, solver, startup_timeout_s: float = 120.0):
        self.solver, self.startup_timeout_s = solver, startup_timeout_s
        self.proc: subprocess.Popen | None = None
        self.started = False

    def _start(self) -> None:
        solver, m = self.solver, self.solver.model
        self.shared = SharedArrays.create(_specs(m, solver.buffers.cand.shape[1]))
        try:
            buffers, self.control = _shared_buffers(solver, self.shared, 0)
            solver.use_buffers(buffers)
            # A plain interpreter running this module (not multiprocessing's spawn, which would re-run the
            # user's __main__ script in the helper); the setup (with the solver's class) travels on its stdin.
            env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
            self.proc = subprocess.Popen(
                [sys.executable, "-c", "from twinbench.physics.split import _helper_main; _helper_main()"],
                stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env,
            )
            pickle.dump((self.shared.path, self.shared.layout, _payload(m), type(solver)), self.proc.stdin)
            self.proc.stdin.flush()
            sync = self.shared.np["sync"]
            t0 = time.monotonic()
            while sync[2] != 1:
                self._alive()
                if time.monotonic() - t0 > self.startup_timeout_s:
                    raise SplitFailed(f"the physics helper did not start in {self.startup_timeout_s:.0f} s")
                time.sleep(0.005)
        except BaseException:
            self.close()
            raise
        finally:
            os.unlink(self.shared.path)  # both processes hold the mapping; the file is not needed any more
        self._finalizer = weakref.finalize(self, _stop, self.proc)
        self.strikes = 0
        self.frame_s: list[float] = []  # the last frames' times, for the stall time-out
        self.barrier = _Barrier(self.shared.np["sync"], 0, 1, self._alive, self._stalled)
        reduce = None
        if m.meshes:  # even and odd substeps' contact forces
            lists, counts = self.shared.np["pm_list"], self.shared.np["pm_count"]
            reduce = tuple(replayable(wp.launch(
                K.reduce_mesh_forces, dim=1, device="cpu", record_cmd=True,
                inputs=[cp, wp.array(lists[k], dtype=int, device="cpu", copy=False),
                        wp.array(counts[k], dtype=int, device="cpu", copy=False), m.meshes_per_world]))
                for k, cp in enumerate(buffers.contacts))
        self.ops: list = []
        self.out = solver.record_frame(self.control, self.ops, _half(m, False), sync=self.barrier,
                                       after_substep=reduce)
        self.started = True

    def _alive(self) -> None:
        if self.shared.np["sync"][3] or self.proc.poll() is not None:
            self.proc.kill()
            err = self.proc.stderr.read().decode(errors="replace").strip().splitlines()
            detail = f": {err[-1]}" if err else ""
            raise SplitFailed(f"the physics helper process failed (exit code {self.proc.wait()}){detail}")

    def _stalled(self, waited: float) -> None:
        self.proc.kill()  # e.g. stopped (SIGSTOP) or starved: waiting on would block the run forever
        self.proc.wait()
        raise SplitFailed(f"the physics helper process stalled (no progress in {waited:.0f} s; a frame takes "
                          f"{1e3 * float(np.median(self.frame_s or [0.0])):.1f} ms)")

    def run_frame(self, state: State, control: Control) -> str | None:
        """One frame from `state` under `control`, split over the two processes, into `state`."""
        if not self.started:
            try:
                self._start()
            except SplitFailed:
                raise
            except Exception as err:  # noqa: BLE001 - one core still works
                raise SplitFailed(str(err)) from err
        t_frame = time.monotonic()
        if self.frame_s:
            self.barrier.timeout_s = max(STALL_TIMEOUT_S, STALL_FRAMES * float(np.median(self.frame_s)))
        s = self.solver
        s.buffers.states[0].assign(state)
        wp.copy(self.control.ctrl_from, control.ctrl_from)
        wp.copy(self.control.ctrl_to, control.ctrl_to)
        if s.has_kinematic_meshes:
            wp.copy(self.control.kin_from, control.kin_from)
            wp.copy(self.control.kin_to, control.kin_to)
            s.set_mesh_velocities(self.control)
        s.update_stiffness()
        try:
            self.proc.stdin.write(b"F")
            self.proc.stdin.flush()
        except OSError as err:
            raise SplitFailed(f"the physics helper process is gone ({err})") from None
        # each side lists the collision candidates of its own particles (the only lists it reads); the frame's
        # first barrier comes before any side writes the positions they are built from again
        s.rebuild_collision_candidates(s.buffers.states[0], rows=(0, s.model.num_particles // 2))
        start_phase, self.barrier.slow = self.barrier.phase, 0
        for op in self.ops:
            op()
        state.assign(self.out)
        self.frame_s = [*self.frame_s[-99:], time.monotonic() - t_frame]
        # Spin barriers need a core each: if other processes keep taking them, one core is faster.
        contended = self.barrier.slow > 0.1 * (self.barrier.phase - start_phase)
        self.strikes = self.strikes + 1 if contended else 0
        return "other processes keep the CPU cores busy" if self.oversubscribed else None

    @property
    def oversubscribed(self) -> bool:
        """CONTENDED_FRAMES frames in a row where over 10 % of the barriers waited for a descheduled process
        (then the solver goes back to one core)."""
        return self.strikes >= CONTENDED_FRAMES

    def close(self) -> None:
        if self.proc is not None:
            _stop(self.proc)
        self.started = False
        self.solver.use_buffers(None)  # contact forces added directly again


def _stop(proc: subprocess.Popen) -> None:
    """End the helper: closing its stdin ends its loop."""
    try:
        proc.stdin.close()
        proc.wait(timeout=2)
    except (OSError, subprocess.TimeoutExpired):
        proc.kill()
        proc.wait()
    proc.stderr.close()


def _helper_main() -> None:
    """The helper process: builds its copy of the model, then runs its half of a frame per byte on stdin."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    watch_parent()
    quiet_warp()
    stdin = sys.stdin.buffer
    path, layout, payload, solver_class = pickle.load(stdin)  # written by our own parent, never a file
    shared = SharedArrays(layout, path, create=False)
    sync = shared.np["sync"]
    try:
        model = _model_from_payload(payload)
        solver = solver_class(model, use_graph=False, threads=1)
        buffers, control = _shared_buffers(solver, shared, 1)
        solver.use_buffers(buffers)

        def parent_alive() -> None:
            if os.getppid() == 1:
                os._exit(75)

        barrier = _Barrier(sync, 1, 0, parent_alive)
        ops: list = []
        solver.record_frame(control, ops, _half(model, True), sync=barrier)
        sync[2] = 1
        n = model.num_particles
        while stdin.read(1) == b"F":
            if solver.has_kinematic_meshes:
                solver.set_mesh_velocities(control)
            solver.rebuild_collision_candidates(solver.buffers.states[0], rows=(n // 2, n))
            for op in ops:
                op()
    except BaseException:
        sync[3] = 1
        raise


__all__ = ["SplitFailed", "SplitFrames", "split_supported", "wants_split"]
