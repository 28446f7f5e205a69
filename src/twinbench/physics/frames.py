"""How a solver's frames run: the executor interface, the buffers a frame writes, the part of a model that a
frame's launches cover, and recorded launches as calls.

A frame executor runs whole frames of a :class:`~twinbench.physics.solver.SpringMassSolver` from launches
the solver records (``solver.record_frame``). The solver picks one: its launches replayed on one core (a
captured graph where possible), groups of worlds on threads (physics.solver), or one world split over two
processes (physics.split). An executor that runs frames elsewhere places the solver's :class:`FrameBuffers`
there (``solver.use_buffers``) before recording, e.g. in memory shared with a helper process.
"""

from __future__ import annotations

import ctypes
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import warp as wp

from . import kernels as K
from .model import Control, SpringMassModel, State


class FrameExecutorFailed(RuntimeError):
    """An executor cannot run frames any more (its state untouched): the solver runs them on one core."""


class FrameExecutor(Protocol):
    """Runs a solver's frames. ``name`` says which kind ("one-core", "threads", "split")."""

    name: str

    def run_frame(self, state: State, control: Control) -> str | None:
        """Advance ``state`` in place by one frame under ``control`` (the solver zeroed the mesh force sums).
        Returns None, or why later frames should run on one core (e.g. it became slower than one core).
        Raises :class:`FrameExecutorFailed`, ``state`` untouched, when it cannot run the frame."""
        ...

    def close(self) -> None:
        """Release the executor's threads or processes and give the solver back its own buffers."""
        ...


@dataclass(frozen=True)
class FrameBuffers:
    """The arrays a frame's launches write besides the forces (which each process keeps to itself)."""

    states: tuple[State, State]  # a frame starts in states[0] and alternates between the two per substep
    ry: wp.array  # per spring: (rest length, effective stiffness or -1 when inactive), set once per frame
    v_star: wp.array  # per particle: the velocity after forces, before collisions
    cand: wp.array  # (particles, width): particle-particle collision candidates, rebuilt once per frame
    cand_count: wp.array  # per particle: its number of candidates
    contacts: tuple[K.ContactParams, K.ContactParams]  # even and odd substeps' contact parameters and sums

    @classmethod
    def allocate(cls, model: SpringMassModel, cand_width: int, contacts: K.ContactParams) -> FrameBuffers:
        dev, n = model.device, model.num_particles
        return cls(
            states=(model.state(requires_grad=False), model.state(requires_grad=False)),
            ry=wp.zeros(model.num_springs, dtype=wp.vec2, device=dev),
            v_star=wp.zeros(n, dtype=wp.vec3, device=dev),
            cand=wp.zeros((n, cand_width), dtype=int, device=dev),
            cand_count=wp.zeros(n, dtype=int, device=dev),
            contacts=(contacts, contacts),
        )


@dataclass(frozen=True)
class Part:
    """The part of a model that one sequence of launches covers: the worlds ``[w0, w1)`` (worlds are laid
    out world-major), or one side of a split frame (``touching`` set)."""

    w0: int
    w1: int
    particles: tuple[int, int]
    springs: tuple[tuple[int, int], ...]  # object springs, then control springs (merged when adjacent)
    kin_vertices: tuple[int, int]
    kinematic: tuple[int, ...]  # kinematic mesh ids
    # a split frame's part: the object springs, then the control springs touching it, in ascending order as
    # launches (control, first, count, ids): a range [first, first + count) when ids is None
    touching: tuple[tuple[bool, int, int, wp.array | None], ...] | None = None


def worlds_part(model: SpringMassModel, w0: int, w1: int) -> Part:
    """The :class:`Part` of the worlds ``[w0, w1)``."""
    nw, W = model.particles_per_world, model.num_worlds
    so = model.num_object_springs // W
    sc = (model.num_springs - model.num_object_springs) // W
    ranges = [(w0 * so, w1 * so), (W * so + w0 * sc, W * so + w1 * sc)]
    if ranges[0][1] == ranges[1][0]:
        ranges = [(ranges[0][0], ranges[1][1])]
    ranges = [r for r in ranges if r[1] > r[0]]
    mw = model.meshes_per_world
    mine = range(w0 * mw, w1 * mw)
    kin = tuple(i for i in mine if model.meshes[i].kinematic)
    ends = [(model.meshes[i].vertex_offset, model.meshes[i].vertex_offset + model.meshes[i].vertices.shape[0])
            for i in kin]
    kv = (ends[0][0], ends[-1][1]) if ends else (0, 0)
    return Part(w0, w1, (w0 * nw, w1 * nw), tuple(ranges), kv, kin)


_ARGS_TYPES: dict = {}  # (kernel, argument types) -> ctypes struct of a CPU kernel's arguments


def replayable(launch) -> Callable[[], None]:
    """A recorded launch (``wp.launch(..., record_cmd=True)``) as a call without arguments.

    On CPU: a direct call of the kernel's compiled entry point with its argument struct packed once. Warp's
    ``Launch.launch()`` packs a ctypes struct of every argument on each call (2-5 us; the contact struct
    costs most), and a frame replays thousands of launches. The struct holds what the recorded launch holds
    (the arrays' addresses, the scalars), so a call is that launch. Where Warp's launch layout is not the
    one this relies on (CUDA, tiles, the adjoint, another Warp version), ``launch.launch``.
    """
    try:
        if not launch.device.is_cpu or launch.adjoint or launch.block_dim > 1:
            return launch.launch
        params = launch.params
        labels = [a.label for a in launch.kernel.adj.args]
        if len(params) != len(labels) + 1:
            return launch.launch
        key = (launch.kernel, tuple(type(p) for p in params[1:]))
        args_type = _ARGS_TYPES.get(key)
        if args_type is None:
            fields = [(name, type(p)) for name, p in zip(labels, params[1:], strict=True)]
            args_type = _ARGS_TYPES[key] = type("Args", (ctypes.Structure,), {"_fields_": fields})
        args = args_type()
        for name, p in zip(labels, params[1:], strict=True):
            setattr(args, name, p)
        forward, bounds, packed = launch.hooks.forward, ctypes.byref(params[0]), ctypes.byref(args)
    except (AttributeError, TypeError, ValueError):
        return launch.launch

    def run() -> None:
        forward(bounds, packed)

    run.launch = launch  # keeps the recorded launch (and the arrays it holds) alive
    run.args = args
    return run
